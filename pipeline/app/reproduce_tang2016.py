"""``magalign reproduce tang2016``: Tang et al. 2016, Eq. (34) and Figure 7, and a tilted table.

More in docs/modules.md, ``pipeline.app.reproduce_tang2016``.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipeline.app import simulate as sim_mod
from pipeline.core.atomic import atomic_path
from pipeline.core.geometry import quat_conj, quat_mul, quat_rotate, so3_exp
from pipeline.core.recording import AngleSeries, ChannelInfo, Recording, Role, VectorSeries
from pipeline.core.style import pyplot
from pipeline.model.tang import (
    HEADING_STATS_KEYS,
    exact_eta,
    fit_alpha_from_eta,
    minor_spin_bound,
    tang_eta,
)
from stages.turntable import fit_axis_tilt, tilt_quat, turntable_quat

F64 = NDArray[np.float64]

FORMAT = "magalign.tang2016/1"
# Tang 2016, Table 2: mean, variance, maximum, minimum (pipeline.model.tang.heading_error_stats)
TABLE2_KEYS = HEADING_STATS_KEYS[:4]


@dataclass(frozen=True)
class TiltedTurntable:
    """An in-memory tilted-turntable recording and its truth."""

    recording: Recording
    q_true_enu_body: F64  # at the magnetometer stamps
    R_body_mag: F64
    B_enu_nT: F64
    tilt_deg: float
    azimuth_deg: float


def simulate_tilted_turntable(
    tilt_deg: float = 3.0,
    azimuth_deg: float = 30.0,
    *,
    rotvec_body_mag_deg: ArrayLike = (2.0, -1.5, 3.0),
    B_enu_nT: ArrayLike = (1500.0, 20000.0, -44000.0),
    mean_rate_deg_s: float = 15.0,
    rate_variation: float = 0.3,
    turns: float = 2.0,
    mag_rate_hz: float = 50.0,
    turntable_rate_hz: float = 100.0,
    noise_nT: float = 20.0,
    seed: int = 0,
) -> TiltedTurntable:
    """Simulate a turntable rotating about an axis tilted from up; returns recording and truth.

    True attitude ``q_true = T q_nom(Omega)`` (model of :mod:`stages.turntable`); the
    turntable channel reports ``Omega`` (unwrapped, rad) at ``turntable_rate_hz``; the
    magnetometer ``R.T C_true.T B + noise`` at ``mag_rate_hz``. The rate varies sinusoidally by
    ``rate_variation`` (relative) so that a time offset would be observable.
    """
    rng = np.random.default_rng(seed)
    w0 = np.radians(mean_rate_deg_s)
    duration = turns * 2 * np.pi / w0
    f_var = 2.0 / duration  # two rate cycles over the run

    def omega(t: F64) -> F64:
        amp = rate_variation * w0 / (2 * np.pi * f_var)
        return w0 * t + amp * (1 - np.cos(2 * np.pi * f_var * t))

    t0 = 1_700_000_000_000_000_000
    t_tt = np.arange(0.0, duration, 1.0 / turntable_rate_hz)
    t_mag = np.arange(0.0, duration, 1.0 / mag_rate_hz)
    R = so3_exp(np.radians(np.asarray(rotvec_body_mag_deg, float)))
    B = np.asarray(B_enu_nT, float)
    T = tilt_quat(tilt_deg, azimuth_deg)
    q_true = quat_mul(T, turntable_quat(omega(t_mag)))
    b_body = quat_rotate(quat_conj(q_true), np.broadcast_to(B, (t_mag.size, 3)))
    y = b_body @ R + noise_nT * rng.standard_normal((t_mag.size, 3))
    mag_t = t0 + np.round(t_mag * 1e9).astype(np.int64)
    tt_t = t0 + np.round(t_tt * 1e9).astype(np.int64)
    rec = Recording(
        path="<tilted turntable>",
        channels=(
            ChannelInfo("/mag", "sensor_msgs/msg/MagneticField", "cdr", Role.MAGNETOMETER,
                        t_mag.size, mag_rate_hz),
            ChannelInfo("/turntable", "std_msgs/msg/Float64", "cdr", Role.TURNTABLE,
                        t_tt.size, turntable_rate_hz),
        ),
        mag=VectorSeries(mag_t, y),
        mag_topic="/mag",
        attitude=None,
        attitude_topic=None,
        turntable=AngleSeries(tt_t, omega(t_tt)),
        mag_frame_id="mag",
    )
    return TiltedTurntable(rec, q_true, R, B, tilt_deg, azimuth_deg)


def _scenario_or_memory() -> tuple[TiltedTurntable, str]:
    """Load the tilted turntable from the simulator's scenario when available, else in memory."""
    scen = Path(__file__).resolve().parents[1] / "scenarios" / "turntable_tilt3.toml"
    try:

        if scen.exists():
            sim = sim_mod.simulate(sim_mod.load_scenario(scen), seed=0)
            truth = sim.truth
            tilt = truth.effects.get("axis_tilt") if isinstance(truth.effects, dict) else None
            rec = sim.recording
            q_true = np.asarray(truth.q_enu_body_true, float)
            if tilt is not None and rec.turntable is not None and q_true.shape[0] == len(rec.mag):
                return (
                    TiltedTurntable(
                        rec, q_true, np.asarray(truth.R_body_mag, float),
                        np.asarray(truth.B_enu_nT, float),
                        float(tilt["tilt_deg"]), float(tilt["azimuth_deg"]),
                    ),
                    "pipeline/scenarios/turntable_tilt3.toml",
                )
    except (ImportError, AttributeError, KeyError, TypeError, ValueError):
        pass
    return simulate_tilted_turntable(), "in-memory (simulate_tilted_turntable, tilt 3 deg, az 30)"


def eta_grid(
    omega_deg: ArrayLike | None = None, alpha_deg: ArrayLike | None = None
) -> dict[str, list]:
    """Eq. (34) and exact azimuth errors on a grid (degrees), one row per alpha."""
    om = np.arange(-40.0, 40.0 + 1e-9, 2.0) if omega_deg is None else np.asarray(omega_deg, float)
    al = np.arange(-20.0, 20.0 + 1e-9, 1.0) if alpha_deg is None else np.asarray(alpha_deg, float)
    om_g, al_g = np.meshgrid(np.radians(om), np.radians(al))
    return {
        "omega_deg": om.tolist(),
        "alpha_deg": al.tolist(),
        "eta_deg": np.degrees(tang_eta(om_g, al_g)).tolist(),
        "eta_exact_deg": np.degrees(exact_eta(om_g, al_g)).tolist(),
    }


def _figure(grid: dict, path: Path) -> None:

    plt = pyplot()

    om = np.asarray(grid["omega_deg"])
    al = np.asarray(grid["alpha_deg"])
    om_g, al_g = np.meshgrid(om, al)
    eta = np.asarray(grid["eta_deg"])
    fig = plt.figure(figsize=(7, 5))
    # 3D axes (mpl_toolkits is untyped; older matplotlib types the result as plain Axes)
    ax: Any = fig.add_subplot(projection="3d")
    ax.plot_surface(om_g, al_g, eta, cmap="viridis", linewidth=0)
    ax.set_xlabel("Omega (deg)")
    ax.set_ylabel("alpha (deg)")
    ax.set_zlabel("eta (deg)")
    ax.set_title("Azimuth error, Tang 2016 Eq. (34) (cf. Figure 7)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def reproduce(out_dir: str | Path) -> int:
    """Write ``tang2016.json`` and the figure into ``out_dir``; print a short table; return 0."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    grid = eta_grid()
    bound = minor_spin_bound()

    # inverse of Eq. (34): recover alpha from azimuth errors generated by exact geometry
    om = np.radians(np.linspace(-40.0, 40.0, 41))
    alpha_true = np.radians(5.0)
    eta_obs = exact_eta(om, alpha_true)
    a34, _ = fit_alpha_from_eta(om, eta_obs)
    aex, _ = fit_alpha_from_eta(om, eta_obs, exact=True)

    sim, source = _scenario_or_memory()
    fits = {}
    cases: dict[str, dict[str, Any]] = {
        "field_unknown": {},
        "field_known": {"reference_field_enu_nT": sim.B_enu_nT},
        "field_and_mounting_known": {
            "reference_field_enu_nT": sim.B_enu_nT,
            "R_known_body_mag": sim.R_body_mag,
        },
    }
    for name, kw in cases.items():
        res = fit_axis_tilt(sim.recording, q_true_enu_body=sim.q_true_enu_body, **kw)
        fits[name] = res.to_dict()

    doc = {
        "format": FORMAT,
        "paper": "Tang, Wang, Yang, Liu 2016, Proc IMechE Part B 230(9) 1771-1777",
        "eta_grid": grid,
        "minor_spin": {
            "omega_max_deg": bound.omega_max_deg,
            "alpha_max_deg": bound.alpha_max_deg,
            "max_minor_spin_deg": bound.max_minor_spin_deg,
            "max_eta_eq34_minus_exact_deg": bound.max_eta_eq34_minus_exact_deg,
            "max_residual_rotation_deg": bound.max_residual_rotation_deg,
        },
        "inverse": {
            "alpha_true_deg": 5.0,
            "alpha_fit_eq34_deg": float(np.degrees(a34)),
            "alpha_fit_exact_deg": float(np.degrees(aex)),
        },
        "turntable": {
            "scenario": source,
            "truth": {"tilt_deg": sim.tilt_deg, "azimuth_deg": sim.azimuth_deg},
            "fits": fits,
        },
        "paper_table2": {"azimuth_variance_before_deg2": 0.1379, "after_deg2": 0.0492},
        # ours beside it: Tang's Table 2 statistics (pipeline.model.tang.heading_error_stats)
        "table2": {
            name: {
                "before": {k: f["heading_before"][k] for k in TABLE2_KEYS},
                "after": None
                if f["heading_after"] is None
                else {k: f["heading_after"][k] for k in TABLE2_KEYS},
            }
            for name, f in fits.items()
        },
    }
    with atomic_path(out / "tang2016.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=2, allow_nan=False))
    _figure(grid, out / "tang2016_fig7.png")

    w = sys.stdout.write
    w(f"Tang 2016 reproduction -> {out}\n")
    w(f"  max minor spin over |Omega|<=40, |alpha|<=20: {bound.max_minor_spin_deg:.3f} deg; "
      f"|Eq.34 - exact| <= {bound.max_eta_eq34_minus_exact_deg:.3f} deg\n")
    w(f"  inverse: alpha 5.000 -> Eq.34 fit {np.degrees(a34):.3f}, "
      f"exact fit {np.degrees(aex):.3f}\n")
    w(f"  tilted table ({source}): truth tilt {sim.tilt_deg:.2f} deg az {sim.azimuth_deg:.1f}\n")
    w("  (heading error = Tang's azimuth error; variances in deg^2; Tang's Table 2: "
      "0.1379 -> 0.0492)\n")
    w(f"  {'case':<26}{'tilt':>8}{'sigma':>9}{'az':>8}{'sigma':>9}{'observable lean':>18}"
      f"{'var_before':>12}{'var_after':>12}\n")

    def num(x: float | None, fmt: str) -> str:
        return format(x, fmt) if x is not None else "inf"

    for name, f in fits.items():
        hb, ha = f["heading_before"], f["heading_after"]
        dirs, sig_obs = f["observable_lean_dirs"], f["sigma_observable_deg"]
        if len(dirs) == 1:  # the lean along the one observable direction, with its sigma
            obs = f"{float(np.dot(dirs[0], f['lean_enu_deg'])):.3f}+-{sig_obs[0]:.1e}"
        else:
            obs = "both" if dirs else "none"
        w(f"  {name:<26}{f['tilt_deg']:8.3f}{num(f['sigma_tilt_deg'], '9.1e'):>9}"
          f"{f['azimuth_deg']:8.1f}{num(f['sigma_azimuth_deg'], '9.1e'):>9}{obs:>18}"
          f"{hb['var_deg2']:12.2e}{ha['var_deg2']:12.2e}\n")
    return 0
