"""Twin subcommands of the ``stereotactip`` CLI (``simulate``); the twin's own benchmark is ``benchmarks.twin_bench``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pipeline.design import DEFAULT_DESIGN

__all__ = ["register", "cmd_simulate"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add this package's subcommands to the top-level parser."""
    from twin.indenters import list_indenters
    from twin.robot import MOTIONS

    p = sub.add_parser("simulate", help="digital twin: press an indenter into a skin, write frames + truth")
    p.add_argument("--design", default=DEFAULT_DESIGN, help="built-in design name or TOML path")
    p.add_argument("--indenter", default="gaussian", help=f"one of: {', '.join(list_indenters())}")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="indenter parameter, repeatable (e.g. sigma2=10; the unit suffix may be dropped); every "
                        "indenter also takes friction=MU, the skin's Coulomb coefficient on the part's material")
    p.add_argument("--depth", type=float, default=5.0, help="press depth, mm (0 = touching the skin)")
    p.add_argument("--steps", type=int, default=1, help="frames captured during the press (depth·k/steps)")
    p.add_argument("--film-every", type=float, default=0.0, metavar="MM",
                   help="also write frames filmed in motion every MM of the press's path (from 1 mm clear of the skin; "
                        "the first at the touch): the skin as a camera sees it while the indenter moves on, flagged "
                        "in_motion in its truth, never valid, for tracking; the settled frames are unchanged")
    p.add_argument("--motion", default="press", choices=MOTIONS)
    p.add_argument("--yaw-deg", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chessboard-pairs", type=int, default=0, metavar="N",
                   help="instead of a press: render N skin-less chessboard pairs (calibration set)")
    p.add_argument("--face-contact", action="store_true",
                   help="the skin's outer faces also collide with spheres on the indenter's tips, crests and steep "
                        "flanks (keeps faces out of sharp indenters; on the 1.5 mm mesh vertices then stand off a "
                        "curved cap, see README 'Contact model')")
    from twin.mesh import NAMED_MESHES

    p.add_argument("--mesh", choices=("auto", *NAMED_MESHES), default="auto",
                   help="skin mesh: 'auto' (default: the mesh the experiments press this indenter on, measured valid "
                        "there: 'axis' for a Gaussian or sphere pressed on the axis, 'sine' for a sine plate, 'face' "
                        "otherwise), 'default' (1.5 mm over the centre, vertex contact unless --face-contact: faces "
                        "0.24 mm inside a sigma2 = 10 Gaussian at 5 mm), 'face' (the same with face contact: the "
                        "terrain taps' and letters'), 'axis' (0.5 mm cells within 3 mm of the sensor axis plus face "
                        "contact: what the Gaussian experiment presses on; ~4x slower than 'default') or 'sine' (1.5 mm "
                        "cells out to 18 mm plus face contact: what the sine experiment presses on, with its plate "
                        "--indenter sine --param relief_radius_mm=13.5 --param roll_off_radius_mm=2)")
    p.add_argument("--friction", type=float, default=None, metavar="MU",
                   help="Coulomb friction skin/indenter for this press (default: the indenter's --param friction=MU, "
                        "else the design's [twin] friction, 1.0 for the built-in "
                        "designs; 0: frictionless). Silicone-type elastomers on hard smooth polymers are usually quoted "
                        "at mu ~ 0.5-1.5 (not measured for Agilus30 on PLA); "
                        "touching vertices stick to the indenter and slide where the tangential force exceeds mu times the "
                        "normal one (README 'Known limits'); presses follow the path (slower)")
    p.add_argument("--allow-invalid", "--allow-unsettled", action="store_true",
                   help="exit 0 even when a frame fails its physics checks (skin inside the indenter beyond "
                        "the bound, press not settled, MuJoCo warnings); the frames are written either way")
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=cmd_simulate)


EXIT_PHYSICS_INVALID = 3   # frames written, but at least one failed its physics checks (see meta.json 'validity')


def report_validity(run) -> list[int]:
    """Print one line per captured frame with its physics checks; returns the indices of invalid frames."""
    bad = []
    for i, v in enumerate(run.meta.get("validity", [])):
        if v is None:
            continue
        if v.get("in_motion"):
            print(f"frame {i:4d}: filmed in motion, penetration max {v['penetration_max_mm']:.3f} mm — not scored")
            continue
        state = "ok" if v["valid"] else "INVALID: " + "; ".join(v["reasons"])
        print(f"frame {i:4d}: penetration max {v['penetration_max_mm']:.3f} mm (p99 {v['penetration_p99_mm']:.3f}), "
              f"force {v['contact_force_n']:.3f} N, settled {'yes' if v['settled'] else 'no'} — {state}")
        if not v["valid"]:
            bad.append(i)
    return bad


def cmd_simulate(args: argparse.Namespace) -> int:
    from pipeline.design import load_design
    from twin import simulate
    from twin.indenters import make_indenter, parse_params

    design = load_design(args.design)
    if design.monocular:
        from pipeline.design import DesignError

        raise DesignError(f"design {design.name!r} is monocular (a TacTip dome): `simulate` drives the stereo "
                          f"modules; its taps run in `stereotactip fit-twin` / `validate` (twin/tactip.py)")
    from twin.gl import setup_gl

    setup_gl()   # a missing GL back end fails here, before the physics runs
    rng = np.random.default_rng(args.seed)
    out = Path(args.out)
    if args.chessboard_pairs:
        from pipeline.io.atomic import atomic_write_json, imwrite_atomic
        from twin.render import render_chessboard_pairs, true_calibration

        t0 = time.perf_counter()
        frames = render_chessboard_pairs(design, args.chessboard_pairs, rng)
        out.mkdir(parents=True, exist_ok=True)
        for i, f in enumerate(frames):
            imwrite_atomic(out / f"frame_{i:04d}.png", f.image)
        true_calibration(design).save_yaml(out / "calib.yaml")
        atomic_write_json(out / "meta.json", {"design": design.name, "chessboard_pairs": len(frames),
                                              "seed": args.seed, "seconds": time.perf_counter() - t0})
        print(f"wrote {len(frames)} chessboard pairs to {out}")
        return 0
    if args.film_every and args.motion != "press":
        from twin.physics import PhysicsError

        raise PhysicsError(f"--film-every {args.film_every:g}: frames in motion are filmed on a press (--motion press), "
                           f"not on {args.motion!r}")
    indenter = make_indenter(args.indenter, **parse_params(args.indenter, args.param))
    t0 = time.perf_counter()
    from twin.mesh import NAMED_MESHES, MeshSpec, auto_mesh

    name = auto_mesh(indenter.name, args.motion) if args.mesh == "auto" else args.mesh
    mesh = MeshSpec(face_contact=True) if args.face_contact and name == "default" else NAMED_MESHES[name]
    print(f"skin mesh: {name}" + (" (--mesh auto: the one the experiments press this indenter on)"
                                  if args.mesh == "auto" else ""))
    if args.motion == "press":
        run = simulate.press(design, indenter, args.depth, n_frames=args.steps, yaw_deg=args.yaw_deg, rng=rng,
                             progress=True, mesh=mesh, friction=args.friction, film_every_mm=args.film_every)
    else:
        run = simulate.run_motion(design, indenter, args.motion, yaw_deg=args.yaw_deg, rng=rng, progress=True,
                                  mesh=mesh, friction=args.friction)
    simulate.write_run(out, design, indenter, run, extra_meta={
        "depth_mm": args.depth, "steps": args.steps, "film_every_mm": args.film_every, "seed": args.seed,
        "yaw_deg": args.yaw_deg, "mesh_choice": args.mesh if args.mesh != "auto" else f"auto: {name}",
        "total_s": time.perf_counter() - t0})
    print(f"wrote {len(run)} frame(s) + truth to {out}")
    bad = report_validity(run)
    if bad:
        print(f"{len(bad)} of {len(run)} frame(s) failed the twin's physics checks (listed above and in "
              f"{out / 'meta.json'}); do not score them against the indenter"
              + ("" if args.allow_invalid else "; exit code 3 (--allow-invalid to accept)"))
        return 0 if args.allow_invalid else EXIT_PHYSICS_INVALID
    return 0
