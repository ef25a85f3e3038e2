"""``stereotactip terrain``: the terrain demonstration (benchmarks/terrain.py) as a subcommand.

:func:`register` adds it to the main parser (``benchmarks/cli.py``); :func:`main` runs it on its own.
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("terrain", help="tap-scan the world relief map, merge the taps, score against the DEM")
    p.add_argument("--regions", default="all",
                   help="'all' or comma-separated region keys: rocky, gulf_of_mexico, andes, drake, "
                        "english_channel, mozambique, black_caspian, himalaya, okhotsk, world")
    p.add_argument("--out", required=True, help="output directory (taps/ inside it make the scan resumable)")
    p.add_argument("--quick", action="store_true", help="two small regions (unless --regions), at most 4 taps each")
    p.add_argument("--workers", type=int, default=None, help="processes for the taps (default: all cores)")
    p.add_argument("--sensor", choices=("ideal", "twin"), default="twin",
                   help="'twin' (default: MuJoCo skin + renderer + the unchanged pipeline; all nine regions, 31 taps, "
                        "took 5 min on 2 cores) or 'ideal' (conforming skin at the marker positions: geometry only)")
    p.add_argument("--tap-z", type=float, default=0.0, dest="tap_z",
                   help="global z (mm, 0 = sea level) of the skin at the bottom of each tap (paper: 0)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cluster", metavar="ADDRESS", default=None,
                   help="run the taps on an existing Dask cluster whose workers share --out, e.g. tcp://10.0.0.5:8786 "
                        "(needs pip install 'stereotactip[cluster]')")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from benchmarks.executor import make_engine
    from benchmarks.terrain import run_scan

    engine = make_engine(cluster=args.cluster) if getattr(args, "cluster", None) else None
    try:
        rec = run_scan(args.out, regions=args.regions, sensor=args.sensor, quick=args.quick, workers=args.workers,
                       tap_z_mm=args.tap_z, seed=args.seed, engine=engine)
    finally:
        if engine is not None:
            engine.close()
    for key, m in rec["regions"].items():
        print(f"{key:16s} taps {m['n_taps']:3d}  RMS {m['rms_err_mm']:.3f} mm  max {m['max_abs_err_mm']:.3f} mm  "
              f"(reachable RMS {m['rms_err_reachable_mm']:.3f})  resolved {m['resolved']}")
    print(f"wrote {args.out}/terrain.json ({rec['n_taps']} taps, {rec['wall_time_s']:.1f} s)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Standalone entry: ``python -m benchmarks.cli_terrain``."""
    from pipeline.errors import UserError
    import sys

    parser = argparse.ArgumentParser(prog="stereotactip")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(argv)
    try:
        return _run(args)
    except UserError as exc:
        print(f"stereotactip terrain: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
