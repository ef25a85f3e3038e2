"""The world relief map: frame, scale, land mask, flattening, STL, DEM loader errors, scan planning."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.types import DataError
from benchmarks import terrain_regions as TR
from twin import dem as D
from twin import terrain as T

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
needs_data = pytest.mark.skipif(not (DATA / "etopo20.cdf").is_file(),
                                reason=f"real ETOPO grids not present in {DATA}")

# the asset is 0.2 deg cells: cell centres lie half a cell (0.0889 mm) inside the print's edges
HALF_CELL_MM = 0.2 * T.MM_PER_DEG / 2 + 1e-9
# bilinear upsampling of a 20' grid to 0.2 deg can shave a peak by at most the source's local
# variation; 300 m (0.2 mm) is well above what a 1/3 deg cell of the Tibetan plateau rises
PEAK_TOL_M = 300.0


@pytest.fixture(scope="module")
def tmap():
    return T.load_terrain_map()


def test_frame_mapping_matches_origin_at_180E_90S():
    # origin at (180 E, 90 S); x eastward from the antimeridian; Greenwich in the middle
    assert T.x_mm_from_lon(180.0) == pytest.approx(0.0)
    assert T.x_mm_from_lon(-180.0) == pytest.approx(0.0)
    assert T.x_mm_from_lon(0.0) == pytest.approx(160.0)
    assert T.x_mm_from_lon(90.0) == pytest.approx(240.0)
    assert T.x_mm_from_lon(-90.0) == pytest.approx(80.0)
    assert T.y_mm_from_lat(-90.0) == pytest.approx(0.0)
    assert T.y_mm_from_lat(90.0) == pytest.approx(160.0)
    lon = np.linspace(-179.9, 179.9, 17)
    np.testing.assert_allclose(T.lon_from_x_mm(T.x_mm_from_lon(lon)), lon, atol=1e-9)
    # vertical scale: -3000 m on the floor, sea level at 2 mm, Everest makes the print 9.7 mm tall
    assert T.z_mm_from_elevation_m(-3000.0) == pytest.approx(0.0)
    assert T.z_mm_from_elevation_m(0.0) == pytest.approx(2.0)
    assert T.BASE_MM + T.z_mm_from_elevation_m(8848.0) == pytest.approx(T.MAP_HEIGHT_MM)


def test_asset_extents_and_flat_ocean(tmap):
    hm = tmap.height_map()
    assert hm.x_mm[0] == pytest.approx(0.0, abs=HALF_CELL_MM) and hm.x_mm[0] > 0
    assert hm.x_mm[-1] == pytest.approx(320.0, abs=HALF_CELL_MM) and hm.x_mm[-1] < 320
    assert hm.y_mm[0] == pytest.approx(0.0, abs=HALF_CELL_MM)
    assert hm.y_mm[-1] == pytest.approx(160.0, abs=HALF_CELL_MM)
    sea = ~tmap.land
    assert 0.25 < tmap.land.mean() < 0.40            # Earth: ~29 % land + Antarctica's ice
    assert np.all(hm.z_mm[sea] == 0.0)                # the ocean floor is exactly flat at 0 mm
    assert np.all(hm.z_mm[tmap.land] >= 0.0)
    assert hm.z_mm.max() <= T.MAP_HEIGHT_MM - T.BASE_MM
    # a point in the open Pacific and one in the Atlantic
    for lat, lon in ((0.0, -150.0), (30.0, -40.0)):
        assert tmap.sample_z_mm(T.x_mm_from_lon(lon), T.y_mm_from_lat(lat)) == pytest.approx(0.0)
    g = tmap.height_map(frame="global")
    assert np.all(g.z_mm[sea] == -T.SEA_LEVEL_MM)


def test_himalaya_highest_point(tmap):
    z = tmap.z_mm
    i, j = np.unravel_index(np.argmax(z), z.shape)
    lat, lon = tmap.lat_deg[i], tmap.lon_deg[j]
    assert 26.0 < lat < 36.0 and 78.0 < lon < 92.0    # the Himalaya / southern Tibet
    assert tmap.x_mm[j] == pytest.approx((lon + 180.0) * 320.0 / 360.0)
    assert tmap.y_mm[i] == pytest.approx((lat + 90.0) * 160.0 / 180.0)
    assert z[i, j] == pytest.approx(2.0 + tmap.elevation_m[i, j] / 1500.0)


@needs_data
def test_highest_point_height_matches_source_dem(tmap):
    dem = D.load_etopo(DATA / "etopo20.cdf")
    src_max = float(np.nanmax(dem.elevation_m))
    assert src_max > 5500                            # Himalaya on a 20' grid
    assert float(tmap.elevation_m.max()) == pytest.approx(src_max, abs=PEAK_TOL_M)
    assert float(tmap.z_mm.max()) == pytest.approx(2.0 + src_max / 1500.0, abs=PEAK_TOL_M / 1500.0)


def test_caspian_is_masked_as_land_below_sea_level(tmap):
    # the Caspian (surface -28 m) is land in the GLOBE mask: kept, not flattened, and below 2 mm
    x, y = T.x_mm_from_lon(50.5), T.y_mm_from_lat(42.0)
    i, j = np.argmin(np.abs(tmap.y_mm - y)), np.argmin(np.abs(tmap.x_mm - x))
    assert tmap.land[i, j]
    assert 1.5 < tmap.z_mm[i, j] < 2.0
    # the Black Sea is connected to the ocean: flattened to the floor
    i, j = np.argmin(np.abs(tmap.lat_deg - 43.0)), np.argmin(np.abs(tmap.lon_deg - 34.0))
    assert not tmap.land[i, j] and tmap.z_mm[i, j] == 0.0


def test_relief_from_dem_flattens_by_mask_not_by_sign():
    lat = np.linspace(-89.5, 89.5, 180)
    lon = np.linspace(-179.5, 179.5, 360)
    LO, LA = np.meshgrid(lon, lat)
    elev = np.where(LO < 0, -100.0, 500.0) + 0 * LA  # western half below sea level
    mask = np.zeros((180, 360), bool)
    mask[:, :90] = True                               # land: the westernmost quarter (negative z)
    mask[:, 270:] = True                              # and the easternmost quarter (positive z)
    tm = T.relief_from_dem(D.Dem(lat, lon, elev, "synthetic"), step_deg=1.0, mask=mask)
    np.testing.assert_allclose(tm.elevation_m[:, :90], -100.0)
    np.testing.assert_allclose(tm.elevation_m[:, 270:], 500.0)
    np.testing.assert_allclose(tm.elevation_m[:, 90:270], -3000.0)   # sea, whatever its sign


def test_stl_is_watertight_with_paper_dimensions(tmap, tmp_path):
    mesh = tmap.to_mesh(stride=6)
    assert mesh.is_watertight and mesh.volume > 0
    (x0, y0, z0), (x1, y1, z1) = mesh.bounds
    assert (x1 - x0, y1 - y0) == (pytest.approx(320.0), pytest.approx(160.0))
    assert z0 == pytest.approx(-T.BASE_MM)
    assert z1 - z0 <= T.MAP_HEIGHT_MM
    # the slab plus the ocean's zero-height floor hold at least 320 x 160 x base of material
    assert mesh.volume > 320 * 160 * T.BASE_MM
    p = tmap.to_stl(tmp_path / "map.stl", stride=12)
    assert p.stat().st_size > 84


@needs_data
@pytest.mark.parametrize("name, shape", [("etopo20.cdf", (540, 1080)), ("etopo60.cdf", (180, 360))])
def test_load_etopo_real_grids(name, shape):
    dem = D.load_etopo(DATA / name)
    assert dem.elevation_m.shape == shape
    assert np.all(np.diff(dem.lon_deg) > 0) and dem.lon_deg[0] >= -180 and dem.lon_deg[-1] < 180
    assert np.all(np.diff(dem.lat_deg) > 0)
    np.testing.assert_allclose(np.diff(dem.lon_deg), 360.0 / shape[1], atol=1e-4)  # wrap column dropped


def _netcdf(path, varname="ROSE"):
    from scipy.io import netcdf_file

    with netcdf_file(str(path), "w") as f:
        f.createDimension("LAT", 4)
        f.createDimension("LON", 8)
        la = f.createVariable("LAT", "f8", ("LAT",)); la[:] = np.linspace(-67.5, 67.5, 4); la.units = "degrees_north"
        lo = f.createVariable("LON", "f8", ("LON",)); lo[:] = np.arange(8) * 45.0; lo.units = "degrees_east"
        v = f.createVariable(varname, "f4", ("LAT", "LON")); v[:] = np.arange(32, dtype=np.float32).reshape(4, 8)


def test_load_etopo_small_file_wraps_longitudes(tmp_path):
    _netcdf(tmp_path / "ok.nc")
    dem = D.load_etopo(tmp_path / "ok.nc")
    np.testing.assert_allclose(dem.lon_deg, [-180, -135, -90, -45, 0, 45, 90, 135])
    assert dem.elevation_m[0, 4] == 0.0 and dem.elevation_m[0, 0] == 4.0   # 180 E moved to -180


@pytest.mark.parametrize("kind", ["missing", "garbage", "truncated", "header_only", "wrong_variable", "text"])
def test_load_etopo_errors_name_the_file(tmp_path, kind):
    good = tmp_path / "good.nc"
    _netcdf(good)
    raw = good.read_bytes()
    bad = tmp_path / f"{kind}.nc"
    if kind == "garbage":
        bad.write_bytes(b"CDF\x01" + bytes(range(256)) * 4)
    elif kind == "truncated":
        bad.write_bytes(raw[: len(raw) - 60])
    elif kind == "header_only":
        bad.write_bytes(raw[:40])
    elif kind == "wrong_variable":
        _netcdf(bad, varname="TEMPERATURE")
    elif kind == "text":
        bad.write_text("not a netcdf file\n")
    with pytest.raises(D.TerrainFileError, match=str(bad.name)) as info:
        D.load_etopo(bad)
    assert isinstance(info.value, DataError)  # a UserError the CLI prints as one line
    if kind == "wrong_variable":
        assert "TEMPERATURE" in str(info.value)


def test_plan_scan_zigzag_covers_box():
    box = (100.0, 140.0, 50.0, 80.0)
    c = TR.plan_scan(box)
    xs, ys = np.unique(c[:, 0]), np.unique(c[:, 1])
    assert len(xs) == 3 and len(ys) == 2 and len(c) == 6
    np.testing.assert_allclose(np.diff(xs), 15.0)
    np.testing.assert_allclose(np.diff(ys), 15.0)
    assert np.mean(xs) == pytest.approx(120.0) and np.mean(ys) == pytest.approx(65.0)
    # boustrophedon: consecutive taps are one step apart (no flyback)
    np.testing.assert_allclose(np.hypot(*np.diff(c, axis=0).T), 15.0)
    # every point of the box lies within step/sqrt(2) of some tap centre
    g = np.stack(np.meshgrid(np.linspace(100, 140, 41), np.linspace(50, 80, 31)), -1).reshape(-1, 2)
    d = np.min(np.linalg.norm(g[:, None] - c[None], axis=2), axis=1)
    assert d.max() <= 15.0 / np.sqrt(2) + 1e-9
    assert len(TR.plan_scan((0, 5, 0, 5))) == 1
    with pytest.raises(DataError):
        TR.plan_scan((5, 0, 0, 5))


def test_regions_are_the_papers_nine(tmap):
    assert len(TR.REGIONS) == 9
    for r in TR.REGIONS.values():
        x0, x1, y0, y1 = r.box_mm()
        assert 0 <= x0 < x1 <= 320 and 0 <= y0 < y1 <= 160
        hm = tmap.crop(r.box_mm())
        has_land = np.any(hm.z_mm > -T.SEA_LEVEL_MM)
        assert has_land, r.key
    assert np.max(tmap.crop(TR.region("himalaya").box_mm()).z_mm) == pytest.approx(np.max(tmap.z_mm) - 2.0)
    with pytest.raises(DataError, match="atlantis"):
        TR.region("atlantis")


def test_tap_indenter_is_the_relief_in_the_downward_sensor_frame(tmap):
    cx, cy = T.x_mm_from_lon(86.0), T.y_mm_from_lat(30.0)
    hm = T.tap_indenter(tmap, (cx, cy), skin_z_mm=0.0, radius_mm=10.0, spacing_mm=0.5)
    # sensor (x_s, y_s) looks at global (cx + x_s, cy - y_s); z_s = skin height - relief
    for xs, ys in ((0.0, 0.0), (5.0, 3.0), (-4.5, -8.0)):
        i, j = np.argmin(np.abs(hm.y_mm - ys)), np.argmin(np.abs(hm.x_mm - xs))
        h = tmap.sample_z_mm(cx + xs, cy - ys, frame="global")
        assert hm.z_mm[i, j] == pytest.approx(0.0 - h)
    assert np.min(hm.z_mm) < -2.0    # Tibet pushes more than 2 mm into a skin pressed to sea level
