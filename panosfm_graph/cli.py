"""The ``panosfm`` command line: each command is a thin layer over a public Python function.

==========  ==============================================================
command     Python function
==========  ==============================================================
run         ``panosfm_graph.pipeline.run_pipeline``
demo        ``panosfm_graph.pipeline.run_demo``
synth       ``panosfm_graph.synth.synthesize``; with ``--panorama`` ``panosfm_graph.synth.cut_spin``;
            ``--phone`` ``panosfm_graph.synth.phone_recording``
import      ``panosfm_graph.phone.import_capture``
inspect     ``panosfm_graph.capture.inspect_capture``
eval        ``panosfm_graph.evaluate.evaluate_reconstruction``
ablate      ``panosfm_graph.ablation.run_ablation``
batch       ``panosfm_graph.batch.run_batch``
view        ``panosfm_graph.viz.view_recording``
==========  ==============================================================

Bad input ends with one line on stderr and exit status 2 (``batch``: bad input to the batch itself;
a failing capture is a line in its index and makes the exit status 1).
"""
from __future__ import annotations

import argparse
import ast
import errno
import json
import logging
import sys
import typing
from pathlib import Path

from .config import SPIN_STYLES, Config, with_overrides, with_spin_style
from .errors import InputError

EXIT_BAD_INPUT = 2
FORMAT_CHOICES = ("auto", "generic", "sensor-logger", "phyphox")  # panosfm_graph.phone.FORMATS (imported lazily)


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 960x540, got {text!r}") from None


def _add_config_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("capture and pipeline settings")
    g.add_argument("--every", type=int, default=None, metavar="K", help="take every K-th frame")
    g.add_argument("--max-frames", type=int, default=None, metavar="N", help="use at most N frames")
    g.add_argument("--scale", type=float, default=None, help="downscale frames and intrinsics by this factor")
    g.add_argument("--normals", choices=["model", "orientation-map", "oracle"], default=None,
                   help="surface-normal source (default: orientation-map; 'model' runs the shipped or --normal-model ONNX network)")
    g.add_argument("--normal-model", default=None, metavar="ONNX", help="run your own ONNX normal model")
    g.add_argument("--camera-height", type=float, default=None, metavar="M",
                   help="camera height above the floor in metres: makes the scale metric")
    g.add_argument("--estimate-focal", action="store_true", default=None,
                   help="estimate the focal length from the Manhattan vanishing points even when camera.json gives "
                        "one (without one, it always is)")
    g.add_argument("--spin", choices=list(SPIN_STYLES), default=None,
                   help="how the capture was spun: hand-held (the stand point wanders), steady (the stand point "
                        "stays put: frames between two fixed ones are placed on the circle) or auto (default: "
                        "hand-held, then steady where the camera centres lie on one circle)")
    g.add_argument("--refine-focal", action="store_true", default=None,
                   help="let the bundle adjustment refine a focal length camera.json gives (default: kept as given; "
                        "an estimated one is always refined where the lines determine it)")
    g.add_argument("--strict", action="store_true", default=None,
                   help="output only the frames an independent solution confirms (the lines' own or the point "
                        "tracks' own places it within 5 %% of the spin's diameter) and no doubtful frame; the lines' "
                        "frames alone: --set graph.motion_model=False")
    g.add_argument("--incremental", type=int, default=None, metavar="N",
                   help="stream the capture N frames at a time: an estimate after each batch, the last solved in "
                        "full (--set graph.incremental_final_solve=False: as the others)")
    g.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="any Config field, e.g. --set relations.floor=False --set graph.robust=cauchy")


def _add_run_options(p: argparse.ArgumentParser, resume_help: str, spawn: bool = True) -> None:
    """Adds the options of ``panosfm run`` after its positionals (shared with ``batch``, which has no --spawn)."""
    p.add_argument("--resume", action="store_true", help=resume_help)
    p.add_argument("--no-rerun", action="store_true", help="do not write recording.rrd")
    if spawn:
        p.add_argument("--spawn", action="store_true", help="open the rerun viewer live")
    _add_config_flags(p)


_TRUE, _FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


def setting_value(section: object, field: str, raw: str, key: str | None = None) -> object:
    """Returns ``raw`` (the text of ``--set SECTION.FIELD=raw``) as the type of that Config field.

    Booleans take true/false, yes/no, on/off, 1/0 in any case (``false`` must never become the truthy
    string "false"); ``none`` sets an optional field to None; anything that does not parse as the
    field's type is an :class:`InputError`.
    """
    hint = typing.get_type_hints(type(section))[field]
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    optional = type(None) in typing.get_args(hint)
    if optional and raw.strip().lower() in ("none", "null"):
        return None
    kind = args[0] if optional and len(args) == 1 else hint
    text = raw.strip()
    try:
        if kind is bool:
            if text.lower() in _TRUE + _FALSE:
                return text.lower() in _TRUE
            raise ValueError
        if kind is int:
            return int(text)
        if kind is float:
            return float(text)
        if kind is str:
            return raw
        value = ast.literal_eval(text)
        if typing.get_origin(kind) is tuple:
            value = tuple(value) if isinstance(value, (list, tuple)) else (value,)
        return value
    except (ValueError, SyntaxError, TypeError):
        name = getattr(kind, "__name__", str(kind))
        raise InputError(f"--set {key or field}={raw}: expected a value of type {name}") from None


def section_settings(section: object, items: list[str], prefix: str) -> dict[str, object]:
    """Returns {field: value} of ``FIELD=VALUE`` items for one Config section (as :func:`setting_value`).

    For the tools that take settings of one section (``tools/bench_linear.py --set spin_links=true``);
    an unknown field is an :class:`InputError` naming ``prefix.FIELD``.
    """
    out = {}
    for item in items or []:
        field, _, raw = item.partition("=")
        if not hasattr(section, field):
            raise InputError(f"--set {item!r}: no setting {prefix}.{field}")
        out[field] = setting_value(section, field, raw, f"{prefix}.{field}")
    return out


def config_from_args(args: argparse.Namespace, base: Config | None = None) -> Config:
    """Returns the Config described by the CLI flags (``--set`` last, so it wins)."""
    cfg = base or Config()
    if getattr(args, "spin", None):
        cfg = with_spin_style(cfg, args.spin)  # before the other flags: --set still wins
    sections: dict[str, dict] = {}

    def put(section: str, field: str, value) -> None:
        if value is not None:
            sections.setdefault(section, {})[field] = value

    put("capture", "every_k", getattr(args, "every", None))
    put("capture", "max_frames", getattr(args, "max_frames", None))
    put("capture", "scale", getattr(args, "scale", None))
    put("normals", "source", getattr(args, "normals", None))
    put("normals", "model_path", getattr(args, "normal_model", None))
    put("linear", "camera_height_m", getattr(args, "camera_height", None))
    put("graph", "incremental_batch", getattr(args, "incremental", None))
    put("focal", "estimate", getattr(args, "estimate_focal", None))
    put("verify", "strict", True if getattr(args, "strict", None) else None)
    put("graph", "refine_given_focal", True if getattr(args, "refine_focal", None) else None)
    for item in getattr(args, "set", []) or []:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise InputError(f"--set {item!r}: expected SECTION.FIELD=VALUE")
        key, raw = item.split("=", 1)
        section, field = key.split(".", 1)
        if not hasattr(cfg, section) or not hasattr(getattr(cfg, section), field):
            raise InputError(f"--set {item!r}: no setting {key!r} (see summary.json's config for the names)")
        put(section, field, setting_value(getattr(cfg, section), field, raw, key))
    try:
        return with_overrides(cfg, **sections)
    except TypeError as exc:
        raise InputError(f"bad setting: {exc}") from None


def _cmd_run(args: argparse.Namespace) -> int:
    from .pipeline import run_pipeline

    result = run_pipeline(args.capture, args.out, config_from_args(args), resume=args.resume,
                          rerun=not args.no_rerun, spawn=args.spawn)
    print(result.report())
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .pipeline import run_demo

    result = run_demo(args.out, scene=args.scene, n_frames=args.frames, size=args.size, seed=args.seed,
                      config=config_from_args(args), spawn=args.spawn)
    print(result.report())
    if "eval" in result.summary:
        from .evaluate import format_metrics

        print("\nagainst the synthetic ground truth:\n" + format_metrics(result.summary["eval"]))
    print(f"\nviews: {result.out_dir / 'views'}/{{quarter,height,topdown}}.png; "
          f"recording: panosfm view {result.out_dir}")
    return 0


def _or(value, default):
    return default if value is None else value


def _cmd_synth(args: argparse.Namespace) -> int:
    scene_only = {"--scene": args.scene, "--texture": args.texture, "--blur": args.blur, "--exposure": args.exposure,
                  "--noise": args.noise, "--sway": args.sway, "--arm": args.arm, "--no-gt-maps": args.no_gt_maps or None,
                  "--tremor": args.tremor, "--phone": args.phone, "--photo-textures": args.photo_textures}
    pano_only = {"--layout": args.layout, "--wobble": args.wobble, "--imu-noise": args.imu_noise}
    parallax = args.panorama is not None and (args.sway is not None or (args.arm or 0.0) > 0)
    if parallax:  # a hand-held spin inside the panorama's room
        given = [k for k, v in scene_only.items() if v is not None and k not in ("--sway", "--arm", "--no-gt-maps")]
        given += ["--wobble"] if args.wobble is not None else []
        if given:
            raise InputError(f"{', '.join(given)}: not for a spin inside a panorama's room (--panorama with --sway "
                             f"or --arm)")
        if args.layout is None:
            raise InputError("--panorama with --sway or --arm spins inside the panorama's room: give its --layout")
        from .synth import room_spin

        extra = {k: v for k, v in dict(hfov_deg=args.hfov, imu_noise_deg=args.imu_noise, turn_deg=args.turn,
                                       arm_m=args.arm).items() if v is not None}
        path = room_spin(args.panorama, args.layout, args.out, n_frames=_or(args.frames, 300),
                         size=_or(args.size, (640, 360)), seed=args.seed, sway_m=_or(args.sway, 0.0),
                         imu_drift_deg=args.imu_drift, gt_maps=not args.no_gt_maps, **extra)
        print(f"wrote {path}")
        return 0
    if args.panorama is not None:
        given = [k for k, v in scene_only.items() if v is not None]
        if given:
            raise InputError(f"{', '.join(given)}: only for synthetic scenes, not with --panorama")
        from .synth import cut_spin

        extra = {k: v for k, v in dict(hfov_deg=args.hfov, wobble_deg=args.wobble, imu_noise_deg=args.imu_noise,
                                       turn_deg=args.turn).items() if v is not None}
        path = cut_spin(args.panorama, args.out, n_frames=_or(args.frames, 240), size=_or(args.size, (640, 360)),
                        seed=args.seed, imu_drift_deg=args.imu_drift, layout=args.layout, **extra)
        print(f"wrote {path}")
        return 0
    given = [k for k, v in pano_only.items() if v is not None]
    if given:
        raise InputError(f"{', '.join(given)}: only with --panorama")
    if args.phone is not None and Path(args.phone).exists() and any(Path(args.phone).iterdir()):
        raise InputError("exists and is not empty", args.phone)
    from .synth import synthesize

    path = synthesize(args.out, scene=_or(args.scene, "living"), n_frames=args.frames,
                      size=_or(args.size, (960, 540)), seed=args.seed, imu_drift_deg=args.imu_drift,
                      turn_deg=args.turn, texture=_or(args.texture, 1.0), sway_m=args.sway,
                      photo_dir=args.photo_textures,
                      blur=_or(args.blur, 0.0), noise=_or(args.noise, 0.0), gt_maps=not args.no_gt_maps,
                      exposure_s=_or(args.exposure, 0.0), arm_m=args.arm, hfov_deg=args.hfov,
                      tremor_deg=_or(args.tremor, 0.0))
    print(f"wrote {path}")
    if args.phone is not None:
        from .synth import phone_recording

        print(f"wrote {phone_recording(path, args.phone, seed=args.seed)} (video.mp4, sensors/: panosfm import "
              f"{Path(args.phone) / 'video.mp4'} {Path(args.phone) / 'sensors'} OUT)")
    return 0


def _cmd_import(args: argparse.Namespace) -> int:
    from .phone import format_import, import_capture

    res = import_capture(args.video, args.sensors, args.out, fmt=args.format, focal_px=args.focal,
                         hfov_deg=args.hfov, offset_guess_s=args.offset_guess, max_offset_s=args.max_offset,
                         line_timing=args.line_timing)
    print(format_import(res))
    return 0


def _cmd_inspect(args: argparse.Namespace) -> int:
    from .capture import format_inspection, inspect_capture

    info = inspect_capture(args.capture)
    print(json.dumps(info, indent=2, default=str) if args.json else format_inspection(info))
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from .evaluate import evaluate_reconstruction, format_metrics

    metrics = evaluate_reconstruction(args.capture, args.out)
    text = format_metrics(metrics)
    print(text)
    if args.json:
        from .export import to_jsonable

        Path(args.json).write_text(json.dumps(to_jsonable(metrics), indent=2))
    return 0


def _cmd_ablate(args: argparse.Namespace) -> int:
    from .ablation import run_ablation

    table = run_ablation(args.capture, args.out, sets=args.sets, config=config_from_args(args))
    print(table)
    return 0


def _batch_install_hint() -> str:
    from .batch import INSTALL_HINT

    return f"Dask distributed ({INSTALL_HINT})"


def _cmd_batch(args: argparse.Namespace) -> int:
    from .batch import run_batch

    result = run_batch(args.captures, args.out, config_from_args(args), scheduler=args.scheduler,
                       workers=args.workers, resume=args.resume, rerun=not args.no_rerun)
    print(result.report())
    return 0 if result.ok else 1


def _cmd_view(args: argparse.Namespace) -> int:
    from .viz import view_recording

    path = Path(args.out)
    view_recording(path / "recording.rrd" if path.is_dir() else path)
    return 0


def _add_import_parser(sub) -> None:
    m = sub.add_parser("import", help="build a capture from a phone video and its raw gyroscope/accelerometer log",
                       description="Build a capture directory from a phone video and its raw sensor log: the time "
                                   "offset and the camera's axes are found from the images, the attitude from a "
                                   "GTSAM AHRS smoother (docs/import.md).")
    m.add_argument("video")
    m.add_argument("sensors", help="sensor log folder or .zip: gyro.csv + accel.csv, a Sensor Logger or a phyphox "
                                   "export")
    m.add_argument("out", help="capture directory to write (must not exist or be empty)")
    m.add_argument("--format", default="auto", choices=FORMAT_CHOICES, help="sensor log layout (default: detected)")
    m.add_argument("--focal", type=float, default=None, metavar="PX",
                   help="focal length in pixels (default: none in camera.json; panosfm run estimates it)")
    m.add_argument("--hfov", type=float, default=None, metavar="DEG", help="horizontal field of view instead of --focal")
    m.add_argument("--offset-guess", type=float, default=None, metavar="S",
                   help="sensor clock minus video clock, roughly (default: from a Sensor Logger video's name, else 0)")
    m.add_argument("--max-offset", type=float, default=5.0, metavar="S",
                   help="search the offset within the guess +- this (default 5)")
    m.add_argument("--no-line-timing", dest="line_timing", action="store_false",
                   help="where the images' turns leave the offset loose (a smooth spin), keep it instead of timing "
                        "the video by the lines' rotations (about 10 s for 300 frames)")
    m.set_defaults(func=_cmd_import)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    p = argparse.ArgumentParser(
        prog="panosfm",
        description="Panoramic structure from motion for indoor 360-degree spin videos (Ikehata et al.).")
    p.add_argument("--version", action="version", version=f"panosfm {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser("run", help="reconstruct a capture directory")
    r.add_argument("capture", help="capture directory (see capture-format.md)")
    r.add_argument("out", help="output directory (replaced atomically when the run completes)")
    _add_run_options(r, "reuse every cached stage whose inputs did not change")
    r.set_defaults(func=_cmd_run)

    d = sub.add_parser("demo", help="synthesise a small capture and reconstruct it")
    d.add_argument("out", help="output directory (capture/ and reconstruction/ go inside)")
    d.add_argument("--scene", default="living")
    d.add_argument("--frames", type=int, default=300)
    d.add_argument("--size", type=_parse_size, default=(960, 540))
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--spawn", action="store_true", help="open the rerun viewer live")
    _add_config_flags(d)
    d.set_defaults(func=_cmd_demo)

    s = sub.add_parser("synth", help="write a synthetic capture with ground truth (a box room, or cut from a panorama)",
                       description="Write a synthetic spin capture with ground truth: ray-cast in a box room "
                                   "(--scene), or cut from a gravity-aligned equirectangular panorama (--panorama: "
                                   "rotation only, every frame shares the panorama's centre).")
    s.add_argument("out")
    s.add_argument("--scene", default=None,
                   help="living (default), bedroom, office, bare, plain, hall, narrow, or random: a procedural room "
                        "and spin drawn from --seed (its frames, turn, sway, arm and field of view unless given)")
    s.add_argument("--panorama", default=None, metavar="PANO",
                   help="cut the spin from this equirectangular image (2:1, horizon on the middle row) instead")
    s.add_argument("--layout", default=None, metavar="FILE",
                   help="with --panorama: the room's layout (PanoAnnotator JSON or HorizonNet corners .txt), for "
                        "ground-truth room lines; with --sway or --arm the spin is hand-held inside that room, its "
                        "surfaces painted with the panorama (parallax)")
    s.add_argument("--frames", type=int, default=None, help="number of frames (default 300; 240 with --panorama)")
    s.add_argument("--size", type=_parse_size, default=None,
                   help="WxH, e.g. 960x540 (default 960x540; 640x360 with --panorama)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--imu-drift", type=float, default=3.0, metavar="DEG", help="IMU heading drift over the turn")
    s.add_argument("--imu-noise", type=float, default=None, metavar="DEG",
                   help="with --panorama: IMU noise per 100 Hz sample, RMS (default 0.3)")
    s.add_argument("--hfov", type=float, default=None, metavar="DEG",
                   help="horizontal field of view (default 64; 65 with --panorama)")
    s.add_argument("--wobble", type=float, default=None, metavar="DEG",
                   help="with --panorama: pitch wobble amplitude, roll half of it (default 2.5)")
    s.add_argument("--turn", type=float, default=None, metavar="DEG", help="how far the person turns (default 380)")
    s.add_argument("--texture", type=float, default=None, help="surface texture strength (default 1; 0 = textureless)")
    s.add_argument("--blur", type=float, default=None, metavar="PX", help="motion blur length (default 0)")
    s.add_argument("--exposure", type=float, default=None, metavar="S",
                   help="exposure time: each frame blurs by it times the spin's angular speed (default 0: sharp)")
    s.add_argument("--noise", type=float, default=None, help="image noise sigma (grey levels, default 0)")
    s.add_argument("--sway", type=float, default=None, metavar="M",
                   help="how far the spin departs from a circle (stand point wandering, arm varying), metres RMS "
                        "(default 0)")
    s.add_argument("--arm", type=float, default=None, metavar="M",
                   help="radius of the circle the camera centre describes (default: 0.30-0.40 m by seed; "
                        "0 = a tripod spin, zero baseline)")
    s.add_argument("--no-gt-maps", action="store_true", help="skip per-frame ground-truth normals and depth")
    s.add_argument("--photo-textures", default=None, metavar="DIR",
                   help="with --scene random: paint some surfaces with crops of the equirectangular photos in DIR")
    s.add_argument("--tremor", type=float, default=None, metavar="DEG",
                   help="RMS angle of a hand's rotational tremor, 2-7 Hz (default 0)")
    s.add_argument("--phone", default=None, metavar="DIR",
                   help="also write the capture as a phone would record it to DIR: video.mp4 and raw gyroscope / "
                        "accelerometer logs (the input of panosfm import)")
    s.set_defaults(func=_cmd_synth)

    _add_import_parser(sub)

    i = sub.add_parser("inspect", help="describe a capture: frames, resolution, IMU coverage, ground truth")
    i.add_argument("capture")
    i.add_argument("--json", action="store_true", help="print JSON instead of a table")
    i.set_defaults(func=_cmd_inspect)

    e = sub.add_parser("eval", help="score a reconstruction directory against the capture's ground truth")
    e.add_argument("capture")
    e.add_argument("out", help="reconstruction directory (sparse/, lines.ply)")
    e.add_argument("--json", default=None, metavar="FILE", help="also write the metrics as JSON")
    e.set_defaults(func=_cmd_eval)

    a = sub.add_parser("ablate", help="run sets of relation/factor types and tabulate the metrics")
    a.add_argument("capture")
    a.add_argument("out")
    a.add_argument("--sets", default="paper",
                   help="'paper', 'factors', or a comma list of factor types, e.g. junction,floor")
    _add_config_flags(a)
    a.set_defaults(func=_cmd_ablate)

    b = sub.add_parser("batch", help="reconstruct many captures on a local or an existing Dask cluster",
                       description="Reconstruct many captures, each as `panosfm run` would, on a local Dask cluster "
                                   "or an existing one (docs/batch.md). Needs " + _batch_install_hint() + ".")
    b.add_argument("captures", nargs="+", metavar="CAPTURE", help="capture directories, or folders holding them")
    b.add_argument("out", metavar="OUT", help="output folder: OUT/<capture>/ per capture, OUT/index.csv and .json")
    b.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="an existing Dask scheduler, e.g. tcp://host:8786 (default: a local cluster on this machine)")
    b.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local cluster: N worker processes, one capture each at a time "
                        "(default: one per core, at most one per capture)")
    _add_run_options(b, "skip captures whose output is complete and current (and those that failed on "
                        "their unchanged input); reuse cached stages for the others", spawn=False)
    b.set_defaults(func=_cmd_batch)

    v = sub.add_parser("view", help="open a saved recording in the rerun viewer")
    v.add_argument("out", help="an output directory or a .rrd file")
    v.set_defaults(func=_cmd_view)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except InputError as exc:
        print(f"panosfm: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EACCES, errno.EROFS, errno.ENOTDIR, errno.EEXIST, errno.EDQUOT):
            target = exc.filename or getattr(args, "out", None)  # a failed write() carries no file name
            where = f"{target}: " if target else ""
            print(f"panosfm: error: {where}{exc.strerror}", file=sys.stderr)
            return EXIT_BAD_INPUT
        raise
    except KeyboardInterrupt:
        print("panosfm: interrupted; the previous result (if any) is untouched", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
