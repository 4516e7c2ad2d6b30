"""A magnet fixed to the platform 1-5 cm from the sensor: one constant offset, named and measured.

A real recording with a magnet fixed 4 cm from the sensor must end as any other does. A
magnet that turns with the sensor adds, whatever its distance, a constant
offset in the sensor's frame: a hard iron, here of 20-100 uT, up to twice the Earth's field.
The independent generator (``tests/indep_gen.py``, no magalign model code) writes the
dipole's field at the sensor as that offset; the diagnosis must end, name the hard iron
alone, measure it and keep the rotation.
"""

from __future__ import annotations

import numpy as np
import pytest
from indep_gen import Spec, write
from scipy.spatial.transform import Rotation

from pipeline.app.commands.diagnose import diagnose_file

#: mu0 / (4 pi), T m / A
MU0_4PI = 1e-7


def dipole_nT(moment_Am2: np.ndarray, r_m: np.ndarray) -> np.ndarray:
    """Field (nT) of a point dipole at offset ``r_m`` from it (the field point minus the dipole)."""
    r = float(np.linalg.norm(r_m))
    u = r_m / r
    return 1e9 * MU0_4PI * (3.0 * float(np.dot(moment_Am2, u)) * u - moment_Am2) / r**3


@pytest.mark.parametrize(("distance_m", "moment_Am2", "seed"), [
    (0.01, 0.0005, 41),  # 1 cm: about 100 uT
    (0.03, 0.004, 42),  # 3 cm: about 30 uT
    (0.05, 0.02, 43),  # 5 cm: about 30 uT
])
def test_a_magnet_fixed_near_the_sensor_is_one_hard_iron(tmp_path, distance_m, moment_Am2,
                                                          seed):
    rng = np.random.default_rng(seed)
    where = distance_m * Rotation.random(random_state=seed).apply([1.0, 0.0, 0.0])
    m = moment_Am2 * Rotation.random(random_state=seed + 100).apply([0.0, 0.0, 1.0])
    offset = dipole_nT(m, -where)  # at the sensor, the magnet at ``where`` from it
    assert 1.5e4 < np.linalg.norm(offset) < 1.5e5  # nT: tens of microtesla
    spec = Spec("attached", seed=int(rng.integers(1000)), duration_s=40.0, mag_noise_nT=2.0,
                effects={"hard_iron": {"offset_nT": offset.tolist()}})
    ctx = diagnose_file(write(spec, tmp_path / "attached.mcap"))
    found = {f.effect: f for f in ctx.diagnosis.findings}
    assert list(found) == ["hard_iron"], list(found)
    est = np.asarray(found["hard_iron"].params["offset_nT"])
    sig = np.asarray(found["hard_iron"].sigma["offset_nT"])
    err = np.abs(est - offset)
    assert np.all((err <= 3 * sig) | (err <= 1.0)), (est, offset, sig)  # nT
    rot = Rotation.from_rotvec(np.radians(ctx.calibration.rotvec_body_mag_deg))
    true = Rotation.from_rotvec(np.radians(spec.rotvec_body_mag_deg))
    assert np.degrees((rot * true.inv()).magnitude()) < 0.02  # deg
