"""Rig calibration keeps the beams of its surfaces (issue 12): the observations are re-segmented
under each new estimate until the surfaces' beam counts settle, so beams further than the reach
from their surface under the first rough estimate (mostly of the later rig poses) come back."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrms import kinematics as k
from lrms.calibration import (
    AdjustOptions,
    Artefact,
    CalibrationError,
    CalibrationOptions,
    Observations,
    calibrate,
)
from lrms.calibration.adjust import MIN_COS, resegment_settled
from sim.scene import SensorModel, continuous_sweep_cloud, get_scene
from sim.scene.library import ROOM_AXIS_POSES, room_axis_artefact

D = np.deg2rad
TRUE_RIG = k.RigModel(
    k0=0.022, k1=700e-6, p=0.1035, q=-0.004, tilt_x=D(0.25), tilt_y=D(-0.1), alpha_zero=D(-0.2), beta_zero=D(0.1),
    beta_scale=-800e-6,
)  # fmt: skip


def pose(t: tuple[float, float, float], yaw_deg: float, tip_deg: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("zx", [yaw_deg, tip_deg], degrees=True).as_matrix()
    m[:3, 3] = t
    return m


def sweeps() -> tuple[list[Observations], dict[int, int]]:
    """Two poses of ``room-spheres-axis`` (-90..90 deg at 30 deg/s); per sphere, the simulated beams
    an adjustment can use (echo, cos(incidence) >= MIN_COS)."""
    scene = get_scene("room-spheres-axis")
    out, usable = [], {}
    for j, (t, yaw, tip) in enumerate(ROOM_AXIS_POSES[:2]):
        cal = k.RigCalibration(model=TRUE_RIG, world_from_rig=pose(t, yaw, tip))
        _, s = continuous_sweep_cloud(scene, cal, SensorModel(), D(-90), D(90), D(30), rng=np.random.default_rng(j))
        v = s.valid
        good = v & (s.cos_incidence >= MIN_COS)
        for i, o in enumerate(scene.objects):
            if o.name.startswith("sphere"):
                a = int(o.name.removeprefix("sphere"))
                usable[a] = usable.get(a, 0) + int(np.count_nonzero(good & (s.index == i)))
        out.append(Observations.from_raw(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v])))
    return out, usable


def test_a_two_pose_calibration_keeps_the_beams_of_its_spheres() -> None:
    obs, usable = sweeps()
    opts = CalibrationOptions(adjust=AdjustOptions(max_plane_points=2000))
    res = calibrate(obs, Artefact.from_dict(room_axis_artefact()), options=opts, poses="separate")
    kept = {sf.artefact_index: sf.points for sf in res.surfaces if sf.kind == "sphere"}
    assert set(kept) == set(range(5))
    # every sphere keeps >= 90 % of the beams simulated on it that meet it at cos(incidence) >=
    # MIN_COS. (This short sweep does not show the loss of the single re-segmentation of before,
    # which kept it too; the bench's 20 deg/s three-pose sweeps do: docs/calibration.md.)
    for a, n in kept.items():
        assert n >= 0.9 * usable[a], (a, n, usable[a])
    assert 2 <= res.residuals["resegmentations"] <= AdjustOptions().max_resegmentations
    truth = TRUE_RIG.canonical()
    std = res.std()
    for name in res.estimated:
        err = getattr(res.model, name) - getattr(truth, name)
        assert abs(err) <= 4 * std[name], (name, err, std[name])


def test_resegmentation_settles_when_no_surface_gains_beams() -> None:
    before = {"plane 0": 10_000, "sphere 1": 2000}
    assert resegment_settled(before, {"plane 0": 10_040, "sphere 1": 2009})
    assert not resegment_settled(before, {"plane 0": 10_000, "sphere 1": 2011})
    assert resegment_settled(before, {"plane 0": 9_000, "sphere 1": 1800})  # only losing: stop
    assert not resegment_settled(before, {"plane 0": 10_000})  # a surface dropped: not settled
    assert not resegment_settled(before, {"plane 0": 10_000, "sphere 2": 2000})


@pytest.mark.parametrize("rounds", [0, -3])
def test_fewer_than_one_resegmentation_is_a_clear_error(rounds: int) -> None:
    with pytest.raises(CalibrationError, match="max_resegmentations must be at least 1"):
        AdjustOptions(max_resegmentations=rounds)
