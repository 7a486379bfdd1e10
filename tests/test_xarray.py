"""The xarray view of a run equals the numpy loader's arrays; NetCDF keeps them."""

import numpy as np
import pytest

from analysis.load import FIELD_UNITS, load_run, open_netcdf
from harness.runs.run import run

TINY = [
    "grid.n=10",
    "agents.n=150",
    "sim.t_final=0.12",
    "sim.dt=0.02",
    "log.field_every=2",
    "log.positions_every=3",
    "log.progress=off",
    "seed=3",
]


@pytest.fixture(scope="module")
def log(tmp_path_factory, compose):
    cfg = compose(TINY)
    out = tmp_path_factory.mktemp("xr")
    assert run(cfg, out).state == "completed"
    return load_run(out)


def test_fields_equal_numpy_loader(log):
    assert {"/fields/p_hat", "/fields/grad_hat", "/fields/velocity"} <= set(log.fields)
    for topic, series in log.fields.items():
        da = log.field_xarray(topic)
        names = series.names
        if len(names) == 1:
            assert da.dims == ("t", "y", "x")
            np.testing.assert_array_equal(da.values, series.values[:, 0])
        else:
            assert da.dims == ("t", "component", "y", "x")
            assert list(da.component.values) == list(names)
            np.testing.assert_array_equal(da.values, series.values)
        np.testing.assert_array_equal(da.t.values, series.t)
        assert da.attrs["units"] == FIELD_UNITS[topic]
        assert da.attrs["field_names"] == " ".join(names)
        assert da.t.attrs["units"] == "s" and da.x.attrs["units"] == "length"


def test_coordinates_are_the_cell_centres(log):
    # grid.n = 10 on the unit square: centres (i + 1/2) / 10, independent of the loader
    da = log.field_xarray("/fields/p_hat")
    centres = (np.arange(10) + 0.5) / 10
    np.testing.assert_allclose(da.x.values, centres, rtol=0, atol=1e-12)
    np.testing.assert_allclose(da.y.values, centres, rtol=0, atol=1e-12)
    # field messages every 2 steps of 0.02 s and at the last step (t = 0.12 s)
    np.testing.assert_allclose(da.t.values, [0.0, 0.04, 0.08, 0.12], rtol=0, atol=1e-12)
    # a density integrates to 1 over the unit square (midpoint rule on the true density)
    p_true = log.field_xarray("/fields/p_true")
    mass = p_true.sum(("x", "y")) * 0.1 * 0.1
    assert mass.dims == ("t",)
    np.testing.assert_allclose(mass.values, 1.0, rtol=1e-5)
    # the velocity component at a cell is the numpy loader's (component, y, x) entry
    v = log.field_xarray("/fields/velocity")
    series = log.fields["/fields/velocity"]
    assert v.sel(component="vy").isel(t=-1, y=3, x=7).item() == series.values[-1, 1, 3, 7]


def test_metrics_equal_numpy_loader(log):
    ds = log.metrics_xarray()
    assert tuple(ds.dims) == ("t",)
    np.testing.assert_array_equal(ds.t.values, log.metrics["t"])
    for key, values in log.metrics.items():
        if key != "t":
            np.testing.assert_array_equal(ds[key].values, values)  # NaN where null
    assert ds.phi_l2.attrs["units"] == "1/length" and ds.t.attrs["units"] == "s"
    assert np.isnan(ds.kde_l2.values).all() == np.isnan(log.metrics["kde_l2"]).all()


def test_netcdf_round_trip(log, tmp_path):
    path = log.to_netcdf(tmp_path / "run.nc")
    assert path.read_bytes()[:3] == b"CDF"  # a netCDF3 file
    ds = open_netcdf(path)
    for key, values in log.metrics.items():
        np.testing.assert_array_equal(ds["t"].values if key == "t" else ds[key].values, values)
    for topic, series in log.fields.items():
        name = topic.removeprefix("/fields/")
        da = ds[name]
        assert da.dtype == np.float32  # the log's precision, stored as such
        values = da.values.astype(float)
        expected = series.values[:, 0] if len(series.names) == 1 else series.values
        np.testing.assert_array_equal(values, expected)
        np.testing.assert_array_equal(ds[f"t_{name}"].values, series.t)
        assert da.attrs["units"] == FIELD_UNITS[topic]
        if len(series.names) > 1:
            assert [str(c) for c in ds[f"component_{name}"].values] == list(series.names)
    np.testing.assert_array_equal(ds.x.values, log.field_xarray("/fields/p_hat").x.values)
    assert ds.attrs["status.state"] == "completed"
    assert ds.attrs["provenance.seed"] == "3"
    assert "grid:" in ds.attrs["config.yaml"]
