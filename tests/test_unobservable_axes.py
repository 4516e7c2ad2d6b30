"""A motion that turns about one axis only: calibration.json names that axis.

Li et al. 2020's Section 4.1 simulation sweeps the heading at a fixed roll, and the field is
not given: the rotation about the one axis the sensor turns about cannot be determined from
such data. The warning names the axis; CONVENTIONS promise it in ``unobservable_axes_body``
too (a list of unit vectors in the body frame), which downstream readers use.
"""

from __future__ import annotations

import json
from importlib.resources import files

import numpy as np
import pytest

from pipeline.app.cli import main
from pipeline.core.geometry import quat_to_matrix
from pipeline.io.mcap_read import read_recording


@pytest.fixture(scope="module")
def li2020(tmp_path_factory):
    root = tmp_path_factory.mktemp("li2020")
    scenario = files("pipeline") / "scenarios" / "li2020_section41.toml"
    rec = root / "li2020.mcap"
    assert main(["simulate", str(scenario), "--out", str(rec)]) == 0
    assert main(["calibrate", str(rec), "--out", str(root / "cal")]) == 0
    cal = json.loads((root / "cal" / "calibration.json").read_text(encoding="utf-8"))
    return read_recording(rec), cal


def test_the_axis_the_motion_turned_about_is_listed(li2020, capsys):
    rec, cal = li2020
    axes = np.asarray(cal["unobservable_axes_body"], float)
    assert axes.shape == (1, 3), cal["unobservable_axes_body"]
    assert abs(np.linalg.norm(axes[0]) - 1.0) < 1e-6
    # the sweep turns about ENU up at a fixed roll: that is this body axis
    up_body = quat_to_matrix(rec.attitude.q_enu_body[0]).T @ np.array([0.0, 0.0, 1.0])
    assert abs(float(axes[0] @ up_body)) > np.cos(np.radians(0.5)), (axes[0], up_body)
    # and the rotation vector's sigma is unbounded (null) where that axis has components
    sig = cal["sigma_rotvec_deg"]
    assert sig[0] is None and sig[2] is None, sig
