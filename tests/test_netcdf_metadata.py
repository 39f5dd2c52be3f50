"""CF-1.10 metadata: every variable and coordinate of every NetCDF (and Zarr) output has a long_name,
numeric ones UDUNITS units, and the file says ``Conventions = "CF-1.10"``.

tests/conftest.py sets ``LOBULA_STRICT_CF=1``, so :func:`experiments.store.write_netcdf` raises on any
file a test writes without them; here the check itself is tested on known datasets, and the main
writers' files are opened and walked on tiny inputs.
"""
from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from experiments.store import CF_CONVENTIONS, STRICT_CF_ENV, cf_problems, strict_cf, units_problem, write_netcdf


def _good() -> xr.Dataset:
    return xr.Dataset(
        dict(v=("time", np.zeros(3), {"units": "m/s", "long_name": "forward velocity"}),
             ok=("time", np.ones(3, bool), {"units": "1", "long_name": "estimate usable"}),
             flag=("time", np.zeros(3, np.int8), {"long_name": "state", "flag_values": np.array([0, 1], np.int8),
                                                  "flag_meanings": "resting moving"}),
             name=("time", np.array(["a", "b", "c"], dtype=object), {"long_name": "label"})),
        coords=dict(time=("time", np.arange(3.0), {"units": "s", "long_name": "time"}),
                    field=("field", ["left", "right"], {"long_name": "field"})),
        attrs=dict(Conventions=CF_CONVENTIONS))


def walk(ds: xr.Dataset) -> list[str]:
    """What this test asks of a written file, checked independently of cf_problems: each variable and
    coordinate a non-empty long_name; each numeric one a non-empty units string (or per-element units)."""
    missing = []
    for name, var in ds.variables.items():
        if not (isinstance(var.attrs.get("long_name"), str) and var.attrs["long_name"].strip()):
            missing.append(f"{name}: long_name")
        if var.dtype.kind in "biufc" and not (isinstance(var.attrs.get("units"), str) and var.attrs["units"].strip()
                                              or "units_coordinate" in var.attrs):
            missing.append(f"{name}: units")
    if ds.attrs.get("Conventions") != CF_CONVENTIONS:
        missing.append(f"Conventions: {ds.attrs.get('Conventions')!r}")
    return missing


def _walk_file(path) -> xr.Dataset:
    """The file's raw attributes (no CF decoding): what a CF reader sees."""
    ds = (xr.open_zarr(path, decode_cf=False) if str(path).endswith(".zarr")
          else xr.open_dataset(path, engine="h5netcdf", decode_cf=False)).load()
    assert walk(ds) == [], path
    assert cf_problems(ds) == [], path
    return ds


# ------------------------------------------------------------------------------------------------ the check
def test_units_problem_accepts_udunits_and_refuses_what_udunits_cannot_parse():
    for ok in ("m/s", "m s-1", "m/s2", "m s-2", "1/s", "s-1", "1/s2", "rad/s", "ms", "Hz", "degree", "1", "s", "m",
               "V", "kHz", "1e-3 m"):
        assert units_problem(ok) is None, ok
    for bad in ("deg", "pixel", "px", "", " ", None, 1, "m/furlong"):
        assert units_problem(bad) is not None, bad


def test_cf_problems_passes_a_described_dataset_and_names_each_gap():
    assert cf_problems(_good()) == []
    bad = _good()
    del bad.attrs["Conventions"]
    del bad["v"].attrs["long_name"]
    bad["ok"].attrs.pop("units")
    bad.coords["time"].attrs["units"] = "deg"
    del bad.coords["field"].attrs["long_name"]
    bad["n"] = ("time", np.arange(3), {"long_name": "count"})  # an integer without units
    bad["flag"].attrs.pop("flag_meanings")                     # flag_values alone describe nothing
    probs = cf_problems(bad)
    assert len(probs) == 7, probs
    for needle in ("Conventions", "variable 'v': no long_name", "variable 'ok': no units",
                   "coordinate 'time': units 'deg'", "coordinate 'field': no long_name", "variable 'n': no units",
                   "variable 'flag': no units"):
        assert sum(needle in p for p in probs) == 1, (needle, probs)
    # Strings need a long_name but no units.
    assert not any("'name'" in p for p in probs)


def test_a_stack_of_metrics_takes_its_units_from_a_coordinate():
    ds = xr.Dataset(dict(value=(("seed", "metric"), np.zeros((2, 2)),
                                {"long_name": "metric", "units_coordinate": "metric_units"})),
                    coords=dict(seed=("seed", [0, 1], {"units": "1", "long_name": "seed"}),
                                metric=("metric", ["rmse_m_s", "lock_on_s"], {"long_name": "metric"}),
                                metric_units=("metric", ["m/s", "s"], {"long_name": "units"})),
                    attrs=dict(Conventions=CF_CONVENTIONS))
    assert cf_problems(ds) == []
    assert cf_problems(ds.assign_coords(metric_units=("metric", ["m/s", "sec."], {"long_name": "units"}))) != []
    assert "units_coordinate" in cf_problems(ds.drop_vars("metric_units"))[0]


def test_write_netcdf_raises_when_strict_and_warns_otherwise(tmp_path, monkeypatch):
    """The test session is strict (tests/conftest.py); a user's run warns and still gets its file."""
    assert strict_cf()  # tests/conftest.py: every file the test session writes is walked
    good = _good()
    del good.attrs["Conventions"]
    written = xr.open_dataset(write_netcdf(good, tmp_path / "good.nc"), engine="h5netcdf")
    assert written.attrs["Conventions"] == CF_CONVENTIONS and "Conventions" not in good.attrs
    assert "_FillValue" not in written.time.encoding  # CF: coordinate variables have no missing values
    bad = good.assign(r_dot=("time", np.zeros(3), {"units": "1/s2"}))
    with pytest.raises(ValueError, match="'r_dot': no long_name"):
        write_netcdf(bad, tmp_path / "bad.nc")
    assert not (tmp_path / "bad.nc").exists()
    monkeypatch.setenv(STRICT_CF_ENV, "0")
    with pytest.warns(UserWarning, match="'r_dot': no long_name"):
        write_netcdf(bad, tmp_path / "bad.nc")
    assert (tmp_path / "bad.nc").exists()


# ------------------------------------------------------------------------------------------------ the writers
@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """2 s of a random track from rest (peak 1 m/s) at quarter scale, and `lobula velocity`'s run.nc on it."""
    from experiments.cli import main

    d = tmp_path_factory.mktemp("cf")
    assert main(["scene", str(d / "scene"), "--duration", "2", "--scale", "0.25", "--peak-speed", "1", "--seed", "0",
                 "--quiet"]) == 0
    assert main(["velocity", str(d / "scene"), "--out", str(d / "run.nc"), "--quiet"]) == 0
    return d


def test_lobula_velocity_file_is_cf(scene):
    ds = _walk_file(scene / "run.nc")
    for name in ("r_dot", "v_field", "gyro_bias_std", "time", "axis"):
        assert ds[name].attrs["long_name"], name
    for name in ("azimuth_deg", "elevation_deg", "size_deg"):
        assert ds[name].attrs["units"] == "degree", name
    assert ds.observable.attrs["units"] == "1" and ds.time.attrs["units"] == "s"
    assert ds.v_field.attrs["units"] == "m/s" and ds.r_dot.attrs["units"] == "1/s2"


@pytest.mark.parametrize("out", ["depth.nc", "depth.zarr"])
def test_lobula_depth_files_are_cf(scene, out):
    from experiments.cli import main

    if out.endswith(".zarr"):
        pytest.importorskip("zarr")
    assert main(["depth", str(scene / "scene"), "--method", "ratio", "--every", "25", "--velocity", "truth",
                 "--velocity-run", str(scene / "run.nc"), "--out", str(scene / out), "--quiet"]) == 0
    ds = _walk_file(scene / out)
    assert "pooled_abs_rel" in ds and ds.attrs["Conventions"] == CF_CONVENTIONS  # scored maps: every variable
    assert ds.x.attrs["units"] == "1" and ds.ring_lo_deg.attrs["units"] == "degree"


def test_lobula_depth_from_a_flo_pair_is_cf(scene):
    """One map from a .flo pair (a radial field in pixels; its depths do not matter here)."""
    pytest.importorskip("torch", reason="a .flo pair is solved by every method, TV on torch (the bio extra)")
    from experiments.cli import main

    W, H = 160, 120
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    flo = scene / "p_000010_to_000016.flo"
    with open(flo, "wb") as fh:
        np.array([202021.25], np.float32).tofile(fh)
        np.array([W, H], np.int32).tofile(fh)
        np.stack([(x - W / 2) * 0.02, (y - H / 2) * 0.02], -1).astype(np.float32).tofile(fh)
    assert main(["depth", str(scene / "scene"), "--flo", str(flo), "--flo-units", "px", "--flo-size", str(W), str(H),
                 "--out", str(scene / "flo.nc"), "--quiet"]) == 0
    ds = _walk_file(scene / "flo.nc")
    assert {"depth", "valid", "frame", "time"} <= set(ds.variables) and ds.frame.attrs["units"] == "1"


def test_lobula_compare_file_is_cf(scene):
    from experiments.cli import main

    assert main(["compare", str(scene / "scene"), "--front-ends", "dis", "--out", str(scene / "compare.nc"),
                 "--quiet"]) == 0
    ds = _walk_file(scene / "compare.nc")
    assert ds.front_end.attrs["long_name"] and ds.azimuth_deg.attrs["units"] == "degree"


def test_lobula_eye_velocity_file_is_cf(tmp_path):
    """The compound eye's run.nc on a second of a coarse eye (two rings, 250 Hz)."""
    pytest.importorskip("torch", reason="the compound eye's circuit runs on torch (the bio extra)")
    from experiments.cli import main
    from lobula.camera import PinholeCamera
    from lobula.compound_eye import CompoundEye, CompoundEyeConfig
    from stimuli.eye import write_eye_footage
    from stimuli.imu import IMUConfig, synthesize_imu
    from stimuli.scene import SceneConfig, TrackScene
    from stimuli.track import builtin_profile
    from stimuli.trajectory import trajectory_from_function

    traj = trajectory_from_function(lambda t: builtin_profile(t + 2.0), 1.0)
    scene = TrackScene(PinholeCamera().scaled(0.25), traj, SceneConfig(seed=5, noise_grey=0.0, mipmap=True))
    eye = CompoundEye(CompoundEyeConfig(dphi_deg=8.0, rings=2))
    times = np.arange(0.0, 1.0, 1 / 250.0)
    fo = write_eye_footage(tmp_path / "eye", scene, eye, synthesize_imu(scene, 1.0, IMUConfig(seed=5)), times, {})
    assert main(["eye-velocity", str(fo), "--accel-from-truth", "--out", str(tmp_path / "eye.nc"), "--quiet"]) == 0
    ds = _walk_file(tmp_path / "eye.nc")
    assert ds.eye.attrs["long_name"] and ds.r_dot.attrs["long_name"] and ds.size_deg.attrs["units"] == "degree"
