"""The whole pipeline on every built-in arm and on arms generated here, as a user runs it:
`jaxcomp calibrate --model M --plan short` in the simulator (recording, both fits), then
`jaxcomp control --mode tracking --model M --params D/params.json` on a 5 cm circle.

The generated arms have no keyframes and no site; one has continuous joints, one is a URDF.
The short plan (one -40..40 deg sweep per joint)
keeps the run short; ``experiments/any_arm_pipeline.py`` runs the default plan and 12 s.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from odd_arms import serial_arm, serial_arm_urdf

from jaxcomp.cli.group import cli
from jaxcomp.recording import load_recording

CIRCLE = "circle:r=0.05,v=0.05"
SETTLE = 3.0  # s
DURATION = 5.0  # s

GENERATED = {
    "continuous7.xml": lambda: serial_arm(11, n=7, continuous=(0, 2, 4, 6)),
    "arm.urdf": lambda: serial_arm_urdf(14, n=6, continuous=(0, 3)),
}


def _model(name: str, tmp_path) -> str:
    if name not in GENERATED:
        return name
    path = tmp_path / name
    path.write_text(GENERATED[name]())
    return str(path)


# gen3 (continuous joints), a gripper and a branched tree run the same path in
# experiments/any_arm_pipeline.py; tests/test_control_any_arm.py tracks them
@pytest.mark.parametrize("name", ["gen3_lite", "wx250s", *GENERATED])
def test_calibrate_fit_and_track(name, tmp_path):
    model = _model(name, tmp_path)
    cal, run = tmp_path / "calibration", tmp_path / "control"
    args = ["calibrate", "--model", model, "--plan", "short", "--out", str(cal)]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 0, out.output + repr(out.exception)
    truth = json.loads((cal / "truth.json").read_text())
    params = json.loads((cal / "params.json").read_text())
    assert params["joints"] == truth["joints"]
    # one sweep per joint already finds most gravity-loaded joints' ratios to a few per cent
    # (a joint gravity never loads, e.g. a base yaw, keeps its type's ratio or the data's
    # scale; a weakly loaded one may be off by more with this short plan), within the
    # standard errors it reports
    excited = np.array([e is not None and e < 0.05 for e in params["diagnostics"]["excitation"]])
    assert excited.sum() >= len(excited) / 2
    ratio_error = np.abs(np.divide(params["ratio"], truth["ratio"]) - 1)[excited]
    assert np.median(ratio_error) < 0.05, ratio_error
    z = (np.subtract(params["ratio"], truth["ratio"]) / params["std"]["ratio"])[excited]
    assert np.median(np.abs(z)) < 2, z
    args = ["control", "--mode", "tracking", "--model", model, "--params", str(cal / "params.json")]
    args += ["--trajectory", CIRCLE, "--duration", str(DURATION), "--out", str(run)]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 0, out.output + repr(out.exception)
    assert "ended: completed" in out.output
    rec = load_recording(run / "recording.npz", require_sweep=False)
    t = rec.t - rec.t[0]
    err = np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)[t >= SETTLE]
    assert np.sqrt(np.mean(err**2)) <= 3e-3
