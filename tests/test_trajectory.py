"""lobula.velocity.trajectory and `lobula velocity --tum`: positions from v̂, the heading and the attitude."""
import numpy as np
from scipy.spatial.transform import Rotation

from lobula.velocity.trajectory import integrate_positions, tum_rows, world_velocity


def test_straight_ahead_at_constant_speed_is_a_line_along_the_turned_axis():
    t = np.linspace(0.0, 2.0, 21)
    yaw = Rotation.from_euler("y", 90, degrees=True).as_quat()  # camera z into world +x
    rows = tum_rows(t, np.full(21, 1.5), np.zeros((21, 2)), np.tile(yaw, (21, 1)))
    np.testing.assert_allclose(rows[:, 0], t)
    np.testing.assert_allclose(rows[:, 1:4], np.column_stack([1.5 * t, 0 * t, 0 * t]), atol=1e-12)
    np.testing.assert_allclose(rows[:, 4:], np.tile(yaw, (21, 1)))


def test_heading_tilts_the_velocity_and_gaps_are_bridged_by_the_last_velocity():
    eye = np.tile([0.0, 0.0, 0.0, 1.0], (5, 1))
    v = world_velocity(np.array([2.0] * 5), np.tile([0.5, -0.25], (5, 1)), eye)
    np.testing.assert_allclose(v[0], [1.0, -0.5, 2.0])
    t = np.arange(6.0)
    vw = np.array([[np.nan] * 3, [1.0, 0, 0], [np.nan] * 3, [np.nan] * 3, [3.0, 0, 0], [3.0, 0, 0]])
    p = integrate_positions(t, vw)
    assert np.all(np.isnan(p[0]))
    np.testing.assert_allclose(p[1:, 0], [0.0, 1.0, 2.0, 4.0, 7.0])


def test_velocity_writes_a_tum_file_that_follows_the_truth(tmp_path, capsys):
    """A scene moving straight ahead: the TUM path's length is the integral of the true speed within 5 %."""
    from experiments.cli import main
    from lobula.readers import open_footage
    from stimuli.track import TrackRunConfig, make_track_run

    folder = make_track_run(tmp_path / "run", TrackRunConfig(start_s=5.0, duration_s=4.0, scale=0.25), progress=False)
    tum = tmp_path / "path.txt"
    assert main(["velocity", str(folder), "--out", str(tmp_path / "v.nc"), "--tum", str(tum), "--quiet"]) == 0
    lines = tum.read_text().splitlines()
    assert lines[0].startswith("# lobula") and lines[1] == "# timestamp tx ty tz qx qy qz qw"
    rows = np.loadtxt(tum)
    assert rows.shape[1] == 8 and len(rows) > 50
    truth = open_footage(folder).truth
    t, v = truth["time_s"], truth["v_forward_m_s"]
    keep = (t >= rows[0, 0]) & (t <= rows[-1, 0])
    travelled = np.trapezoid(v[keep], t[keep])
    assert abs(travelled) > 0.2  # it moved: the bound below means something
    assert abs(rows[-1, 3] - travelled) < 0.05 * abs(travelled)
