"""Regenerate ``relief.npz`` (the terrain demonstration's land relief) from an ETOPO-family netCDF.

Usage::

    python sim_assets/terrain/make_relief.py /path/to/etopo20.cdf [--step-deg 0.2] [--out relief.npz]

Any ETOPO-family grid works: the Ferret ETOPO5/20/60 netCDF-3 files (variable ROSE), ETOPO1, and
the 30 arc-second ETOPO 2022 surface grid (netCDF-4: needs ``pip install h5py``; about 3.7 GB in
memory as float32). Steps: read (longitudes wrapped to [-180, 180), wrap column dropped), resample to
a global cell-centred grid of ``--step-deg`` (area mean when the source is finer, bilinear when it is
coarser), decide land with the 1 km GLOBE land mask (``global_land_mask``, majority of 3x3 samples per
cell), keep land relief (clipped at -3000 m), set every sea cell to -3000 m, store int16 metres + packed
land bits + the grid definition + the source's name and sha256. See twin/terrain.py for the map frame
and vertical scale built on top of it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))  # run from a checkout without installing

from twin.dem import load_etopo  # noqa: E402
from twin.terrain import file_sha256, relief_from_dem  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dem", type=Path, help="ETOPO-family netCDF file")
    p.add_argument("--step-deg", type=float, default=0.2, help="output grid step (deg), default 0.2")
    p.add_argument("--variable", default=None, help="relief variable name (default: ROSE, z, ...)")
    p.add_argument("--out", type=Path, default=HERE / "relief.npz")
    a = p.parse_args(argv)
    dem = load_etopo(a.dem, variable=a.variable)
    sha = file_sha256(a.dem)
    tmap = relief_from_dem(dem, step_deg=a.step_deg, progress=True)
    tmap.save_npz(a.out, extra={"source_sha256": sha, "source_name": a.dem.name,
                                "source_step_deg": dem.step_deg})
    print(f"{a.out}: {tmap.land.shape[1]}x{tmap.land.shape[0]} cells of {a.step_deg} deg, "
          f"land {tmap.land.mean():.3f}, elevation {tmap.elevation_m.min():.0f}..{tmap.elevation_m.max():.0f} m, "
          f"{a.out.stat().st_size / 1e6:.2f} MB; source {a.dem.name} sha256 {sha}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
