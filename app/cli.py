"""The ``floornav`` command line (also ``python -m app``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

from app.config import DEFAULT_CONFIG_PATH, ConfigError, FloornavConfig, load_config
from app.fileio import print_json
from app.mapping.calibrate_cli import add_calibrate_parser

PROJECT_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATASETS_DIR = PROJECT_ROOT.parent / "shared" / "datasets"


def _load(path: Path) -> FloornavConfig:
    return load_config(path)


def cmd_validate_config(args: argparse.Namespace) -> int:
    try:
        load_config(args.path)
    except ConfigError as exc:
        print(f"{exc.source}: {len(exc.issues)} error(s)")
        for issue in exc.issues:
            print(f"  {issue}")
        return 1
    print("ok")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from app.daemon import run_daemon

    # Validated before any device is touched: a bad key (or world name) exits 2 naming it.
    sim: dict[str, object] = {}
    if args.world is not None:
        sim["world_file"] = args.world
    if args.seed is not None:
        sim["seed"] = args.seed
    config = load_config(args.config, sim=sim) if sim else _load(args.config)
    if args.duration_s is not None and not args.duration_s > 0:
        raise ValueError(f"--duration-s must be > 0, got {args.duration_s}")
    record: Path | None = args.record
    if record is not None and record.suffix.lower() != ".mcap":
        raise ValueError(f"--record writes MCAP: name a .mcap file, got {record}")
    if record is not None and record.exists():
        raise ValueError(f"--record {record}: the file exists; it is never overwritten")
    return run_daemon(
        config,
        config_source=str(args.config),
        duration_s=args.duration_s,
        report_path=args.report,
        map_path=args.map,
        record_path=record,
    )


def cmd_warmup(args: argparse.Namespace) -> int:
    """Compile (or load from numba's cache) every kernel ``floornav run`` will call, so
    that even its first run starts from the cache."""
    from app.jit import compile_kernels

    report = compile_kernels(_load(args.config))
    print(report.banner_line().strip(), flush=True)
    return 0


def _check_segment_args(args: argparse.Namespace) -> None:
    """Refuse option mixes that would overwrite outputs, before any image is read."""
    images: list[Path] = args.images
    if args.out is not None and len(images) > 1:
        raise ValueError(
            f"--out names one overlay file but {len(images)} images were given "
            "(use --mask-out DIR, with --overlay for overlays there)"
        )
    if args.mask_out is not None or args.overlay:
        stems: dict[str, Path] = {}
        for path in images:
            if path.stem in stems and stems[path.stem] != path:
                raise ValueError(
                    f"{stems[path.stem]} and {path} would both write {path.stem}_floor.*"
                )
            stems[path.stem] = path


def cmd_segment(args: argparse.Namespace) -> int:
    """Segment each image; write its mask (--mask-out) and/or its overlay.

    An unreadable image is reported on stderr and skipped so one bad file in a batch
    does not lose the others' masks; the exit code is then 1.
    """
    import time

    import numpy as np

    from app.imageio import ImageFileError, read_bgr, write_image_atomic
    from app.perception.overlay import draw_overlay
    from app.perception.pipeline import FloorSegmenter

    _check_segment_args(args)
    mask_dir: Path | None = args.mask_out
    # Without --mask-out the command writes overlays as it always did.
    write_overlay = mask_dir is None or args.out is not None or args.overlay
    config = _load(args.config)
    segmenter = FloorSegmenter(config.perception, method=args.method)
    if mask_dir is not None:
        mask_dir.mkdir(parents=True, exist_ok=True)
    failed = 0
    for path in args.images:
        try:
            image = read_bgr(path)
        except ImageFileError as exc:
            print(f"floornav: error: {exc}", file=sys.stderr)
            failed += 1
            continue
        start_s = time.perf_counter()
        result = segmenter.segment(image)
        segment_ms = (time.perf_counter() - start_s) * 1e3
        height, width = image.shape[:2]
        written = []
        if mask_dir is not None:
            mask_path = mask_dir / f"{path.stem}_floor.png"
            mask = np.where(result.floor_mask, 255, 0).astype(np.uint8)
            write_image_atomic(mask_path, mask)
            written.append(f"mask {mask_path}")
        if write_overlay:
            overlay = draw_overlay(
                image,
                result.floor_mask,
                safe_zone_corners_px=segmenter.zone.corners_px(width, height),
                labels=result.labels,
            )
            overlay_dir = mask_dir if mask_dir is not None else Path()
            out = args.out or overlay_dir / f"{path.stem}_floor.overlay.png"
            write_image_atomic(out, overlay)
            written.append(f"overlay {out}")
        floor_pct = 100.0 * float(result.floor_mask.mean())
        print(
            f"{path}: method {result.method}, floor {floor_pct:.1f}%, {segment_ms:.1f} ms"
            f" -> {', '.join(written)}"
        )
    return 1 if failed else 0


def cmd_eval(args: argparse.Namespace) -> int:
    from app.evaluation import evaluate, format_table, stderr_progress
    from app.perception.pipeline import METHODS

    config = _load(args.config)
    methods = _methods(args.method, config, METHODS)
    if args.cv:
        return _eval_cv(args, config, methods)
    if args.folds is not None:
        raise ValueError("--folds needs --cv")
    report = evaluate(args.folders, methods, config.perception, progress=stderr_progress)
    summary = report.summary(config.perception.method)
    if args.json:
        print_json(summary)
    else:
        print(format_table(summary))
    scored = any(
        scores for by_method in report.per_dataset.values() for scores in by_method.values()
    )
    if not scored:
        print("floornav eval: no labelled image could be scored", file=sys.stderr)
    return 0 if scored else 1


def cmd_eval_video(args: argparse.Namespace) -> int:
    from app.perception.pipeline import METHODS
    from app.video_eval import evaluate_videos, format_video_table, stderr_progress

    config = _load(args.config)
    methods = sorted(METHODS) if args.method == "all" else [args.method or config.perception.method]
    summary = evaluate_videos(
        args.videos,
        methods,
        config.perception,
        stride=args.stride,
        max_frames=args.max_frames,
        progress=stderr_progress,
    )
    if args.json:
        print_json(summary)
    else:
        print(format_video_table(summary))
    if not summary["videos"]:
        print("floornav eval-video: no video could be read by any method", file=sys.stderr)
        return 1
    return 0


def _methods(option: str | None, config: FloornavConfig, known: Iterable[str]) -> list[str]:
    """``--method``: a name, comma-separated names, or ``all``; default from the config."""
    if option == "all":
        return sorted(known)
    return (option or config.perception.method).split(",")


def _eval_cv(args: argparse.Namespace, config: FloornavConfig, methods: list[str]) -> int:
    from app.crossval import cross_validate, format_cv_table
    from app.crossval import stderr_progress as cv_progress

    if args.folds is not None and args.folds < 2:
        raise ValueError(f"--folds must be at least 2, got {args.folds}")
    summary = cross_validate(
        args.folders, methods, config.perception, n_folds=args.folds, progress=cv_progress
    )
    if not args.per_image:
        summary.pop("per_image", None)
    if args.json:
        print_json(summary)
    else:
        print(format_cv_table(summary))
    return 0


def cmd_eval_superpixels(args: argparse.Namespace) -> int:
    from app.evaluation import evaluate_superpixels, format_superpixel_table, stderr_progress

    config = _load(args.config)
    summary = evaluate_superpixels(args.folders, config.perception, progress=stderr_progress)
    if args.json:
        print_json(summary)
    else:
        print(format_superpixel_table(summary))
    return 0


def cmd_sim_eval(args: argparse.Namespace) -> int:
    from app.evaluation import evaluate_on_simulator
    from app.perception.pipeline import METHODS

    config = _load(args.config)
    methods = sorted(METHODS) if args.method == "all" else [args.method or config.perception.method]
    summary = evaluate_on_simulator(config, methods, frames=args.frames)
    if args.json:
        print_json(summary)
    else:
        print(f"{summary['frames']} simulated frames of world {summary['world']!r}")
        print(f"{'method':<18}{'iou':>8}{'recall':>9}{'precision':>11}{'near_FF':>9}")
        scores = summary["methods"]
        assert isinstance(scores, dict)
        for method, s in scores.items():
            print(
                f"{method:<18}{s['iou']:>8.3f}{s['floor_recall']:>9.3f}"
                f"{s['floor_precision']:>11.3f}{s['near_false_floor']:>9.3f}"
            )
    return 0


def cmd_uno_check(args: argparse.Namespace) -> int:
    import asyncio

    from app.devices import open_uno
    from app.hardware.uno_check import run_uno_check

    config = _load(args.config)
    with open_uno(config.serial) as uno:
        report = asyncio.run(
            run_uno_check(
                uno.port,
                config.serial,
                pings=args.pings,
                drive_pwm=args.drive_pwm,
                drive_s=args.drive_s,
            )
        )
    if args.json:
        print_json(report)
    else:
        for key, value in report.items():
            print(f"{key}: {value}")
    return 0 if report.get("connected") else 1


BENCH_SECTIONS = ("perception", "grid", "render", "daemon")


def cmd_bench(args: argparse.Namespace) -> int:
    from app.benchmarks import pin_to_one_cpu, restored_affinity

    config = _load(args.config)
    perception = config.perception.model_copy(
        update={"method": args.method or config.perception.method}
    )
    sections = args.only or BENCH_SECTIONS
    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames}")
    result: dict[str, object] = {"method": perception.method}
    blocks: list[str] = []  # the text report, section by section
    with restored_affinity():
        result["pinned"] = pin_to_one_cpu()
        # Lazy imports: a section loads only its own subsystem (perception alone needs
        # neither the runtime nor the simulator).
        if "perception" in sections:
            from app.benchmarks.perception import format_bench, run_bench

            result |= run_bench(perception, args.datasets, repeats=args.repeats)
            blocks.append(format_bench(result))
        if "grid" in sections:
            from app.benchmarks.grid import bench_grid_update, format_grid_bench

            grid = bench_grid_update(max(1, args.repeats))
            result["grid_update"] = grid
            blocks.append(format_grid_bench(grid))
        if "render" in sections:
            from app.benchmarks.sim import bench_render

            render = bench_render(max(1, args.repeats // 2))
            result["sim_render"] = render
            blocks.append(
                f"== simulator render 640x480 ({render['frames']} frames): median "
                f"{render['median']:.2f} ms, min {render['min']:.2f}, max {render['max']:.2f}"
                f" -> {render['fps']:.0f} fps"
            )
        if "daemon" in sections:
            from app.benchmarks.frame_path import bench_frame_path, format_frame_path

            daemon_config = config.model_copy(update={"perception": perception})
            frame_path = bench_frame_path(daemon_config, args.frames)
            result["daemon_frame_path"] = frame_path
            blocks.append(format_frame_path(frame_path))
    if args.json:
        print_json(result)
    else:
        print("\n\n".join(blocks))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="floornav",
        description="Monocular floor segmentation, mapping and navigation for an indoor robot.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def add_config(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--config", type=Path, default=DEFAULT_CONFIG_PATH, help="config file (TOML)"
        )

    p = sub.add_parser("validate-config", help="check a config file; print 'ok' or each error")
    p.add_argument("path", type=Path, nargs="?", default=DEFAULT_CONFIG_PATH)
    p.set_defaults(func=cmd_validate_config)

    p = sub.add_parser("run", help="run the daemon (the simulator with the shipped config)")
    p.add_argument("--duration-s", type=float, help="stop after this many seconds")
    p.add_argument("--report", type=Path, help="write a JSON run report here at exit")
    p.add_argument(
        "--map",
        type=Path,
        metavar="FILE",
        help="continue the map saved in FILE (if it exists) and save it there at exit, "
        "with a ROS map_server copy beside it (FILE.pgm, FILE.yaml)",
    )
    p.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="record the run to FILE.mcap (camera, floor masks, odometry, commands, stops, "
        'map, logs; Foxglove schemas); replay it with [camera] source = "replay"',
    )
    p.add_argument(
        "--world",
        metavar="NAME",
        help="simulated world: a shipped one (two-rooms, home, office; default: two-rooms) "
        "or the path of a world .toml file (sets [sim] world_file)",
    )
    p.add_argument(
        "--seed",
        type=int,
        metavar="S",
        help="seed of the simulator's random draws (sets [sim] seed, 0 by default)",
    )
    add_config(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "warmup",
        help="compile the numba kernels `run` uses into numba's cache (scripts/setup does)",
    )
    add_config(p)
    p.set_defaults(func=cmd_warmup)

    p = sub.add_parser(
        "segment", help="segment the floor in images; write floor masks and/or overlays"
    )
    p.add_argument("images", type=Path, nargs="+", metavar="IMAGE")
    p.add_argument("--method", help="segmentation method (default: from config)")
    p.add_argument(
        "--out",
        type=Path,
        help="overlay PNG, one IMAGE only (default: NAME_floor.overlay.png, in DIR with "
        "--mask-out)",
    )
    p.add_argument(
        "--mask-out",
        type=Path,
        metavar="DIR",
        help="write DIR/NAME_floor.png per image (8-bit, 255 = floor); no overlays then "
        "unless --out or --overlay",
    )
    p.add_argument(
        "--overlay",
        action="store_true",
        help="with --mask-out, also write DIR/NAME_floor.overlay.png",
    )
    add_config(p)
    p.set_defaults(func=cmd_segment)

    p = sub.add_parser("eval", help="score methods on folders of NAME.jpg + NAME_floor.png")
    p.add_argument("folders", type=Path, nargs="+", metavar="DIR")
    p.add_argument(
        "--method", help="a method name, names joined by commas, or 'all' (default: from config)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--cv",
        action="store_true",
        help="out-of-scene scores: refit each method without the held-out scenes",
    )
    p.add_argument(
        "--folds",
        type=int,
        help="with --cv: folds of whole scenes (default: leave one scene out)",
    )
    p.add_argument(
        "--per-image", action="store_true", help="with --cv --json: every image's scores too"
    )
    add_config(p)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser(
        "eval-video",
        help="label-free checks on videos: mask stability, bottom-half floor, ms per frame",
    )
    p.add_argument("videos", type=Path, nargs="+", metavar="VIDEO")
    p.add_argument("--method", help="a method name, or 'all' (default: from config)")
    p.add_argument("--stride", type=int, default=1, help="process every Nth frame (default 1)")
    p.add_argument("--max-frames", type=int, help="process at most N frames of each video")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_config(p)
    p.set_defaults(func=cmd_eval_video)

    p = sub.add_parser(
        "eval-superpixels",
        help="boundary recall and undersegmentation error of each SLIC backend",
    )
    p.add_argument("folders", type=Path, nargs="+", metavar="DIR")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_config(p)
    p.set_defaults(func=cmd_eval_superpixels)

    add_calibrate_parser(sub)

    p = sub.add_parser("sim-eval", help="floor masks on simulated frames vs ground truth")
    p.add_argument("--method", help="a method name, or 'all' (default: from config)")
    p.add_argument("--frames", type=int, default=30, help="frames along the path")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_config(p)
    p.set_defaults(func=cmd_sim_eval)

    p = sub.add_parser(
        "uno-check", help="connect to the configured Uno, handshake, measure round trips"
    )
    p.add_argument("--pings", type=int, default=50, help="PING round trips to time")
    p.add_argument("--drive-pwm", type=int, default=0, help="drive both wheels at this PWM")
    p.add_argument("--drive-s", type=float, default=0.0, help="... for this many seconds")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_config(p)
    p.set_defaults(func=cmd_uno_check)

    p = sub.add_parser("bench", help="time the pipeline's stages against the reference")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--repeats", type=int, default=5, help="passes over the bench images")
    p.add_argument("--method", help="the segmentation method to time (default: from config)")
    p.add_argument(
        "--datasets", type=Path, default=DEFAULT_DATASETS_DIR, help="the shared datasets folder"
    )
    p.add_argument(
        "--frames", type=int, default=60, help="simulated frames for the daemon's per-frame path"
    )
    p.add_argument(
        "--only",
        action="append",
        choices=BENCH_SECTIONS,
        help="run just this section (repeatable; default: all)",
    )
    add_config(p)
    p.set_defaults(func=cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code: int = args.func(args)
    except ConfigError as exc:
        print(f"floornav: {exc}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        print(f"floornav: error: {exc}", file=sys.stderr)
        return 1
    return code


if __name__ == "__main__":
    raise SystemExit(main())
