"""`fleetmap`: the command line for robots' data, the services and the main job."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from tqdm import tqdm

from shared.camera import Intrinsics
from shared.errors import FleetmapError

log = logging.getLogger("fleetmap")


def _add_camera_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("camera overrides (default: camera.json, else TUM fr1)")
    for name in ("fx", "fy", "cx", "cy"):
        g.add_argument(f"--{name}", type=float)
    g.add_argument("--depth-scale", type=float, help="depth units per metre (TUM: 5000)")


def _add_keyframe_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("keyframe selection")
    g.add_argument(
        "--kf-translation",
        type=float,
        default=0.05,
        metavar="M",
        help="new keyframe after moving this far (default 0.05 m)",
    )
    g.add_argument(
        "--kf-rotation",
        type=float,
        default=5.0,
        metavar="DEG",
        help="new keyframe after turning this much (default 5 deg)",
    )
    g.add_argument(
        "--kf-interval",
        type=float,
        default=1.0,
        metavar="S",
        help="new keyframe after this long at the latest (default 1 s)",
    )


def _add_bag_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("ROS bags (.bag, or a ROS 2 bag folder): topics where ambiguous")
    g.add_argument("--rgb-topic", help="sensor_msgs/Image colour topic")
    g.add_argument("--depth-topic", help="sensor_msgs/Image depth topic (16UC1 mm, 32FC1 m)")
    g.add_argument("--info-topic", help="sensor_msgs/CameraInfo topic")
    g.add_argument("--pose-topic", help="PoseStamped or Odometry: camera in the map frame")


def _topics(args: argparse.Namespace):
    from shared.bags import BagTopics

    return BagTopics(*(getattr(args, f"{k}_topic", None) for k in ("rgb", "depth", "info", "pose")))


def cmd_convert(args: argparse.Namespace) -> int:
    """A ROS bag robot written out as a TUM folder."""
    from shared.bags import bag_to_tum, is_bag
    from shared.dataset import read_recording

    src, out = Path(args.bag), Path(args.output)
    if not is_bag(src):
        from shared.errors import BadRobotData

        raise BadRobotData(f"{src}: not a ROS bag (.bag, or a folder with metadata.yaml)")
    if out.exists():
        from shared.errors import BadInput

        raise BadInput(f"{out} exists: give a new folder")
    bag_to_tum(src, out, _topics(args))
    rec = read_recording(out)
    print(f"{len(rec)} RGB-D frames with poses -> {out}")
    return 0


def _intrinsics(args: argparse.Namespace, robot_dir: Path) -> Intrinsics | None:
    overrides = {
        k: getattr(args, k)
        for k in ("fx", "fy", "cx", "cy", "depth_scale")
        if getattr(args, k, None) is not None
    }
    if not overrides:
        return None
    from shared.dataset import read_recording

    base = read_recording(robot_dir, topics=_topics(args)).intrinsics.to_dict()
    return Intrinsics.from_dict({**base, **overrides})


def _read_robots(args: argparse.Namespace, robot_args: list[str]) -> list:
    """Recordings with depth and poses for [NAME=]DIR arguments."""
    from shared.dataset import parse_robot_arg, read_recording

    recs = []
    for arg in robot_args:
        name, robot_dir = parse_robot_arg(arg)
        recs.append(
            read_recording(
                robot_dir,
                name,
                _intrinsics(args, robot_dir),
                require_depth=True,
                require_poses=True,
                topics=_topics(args),
            )
        )
    return recs


def _policy(args: argparse.Namespace):
    from shared.keyframes import KeyframePolicy

    return KeyframePolicy(args.kf_translation, args.kf_rotation, args.kf_interval)


def cmd_extract(args: argparse.Namespace) -> int:
    """Write one encoded frame structure per keyframe of a robot folder."""
    from shared.dataset import parse_robot_arg, read_recording
    from shared.extract import FrameExtractor, extract_recording, keyframe_indices
    from shared.frame import encode
    from shared.vocabulary import load_vocabulary

    name, robot_dir = parse_robot_arg(args.robot)
    rec = read_recording(robot_dir, name, _intrinsics(args, robot_dir), topics=_topics(args))
    extractor = FrameExtractor(load_vocabulary(args.vocab))
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    n = len(keyframe_indices(rec, _policy(args)))
    total = 0
    frames = extract_recording(rec, extractor, _policy(args))
    for frame in tqdm(frames, total=n, desc=f"extract {rec.robot_id}", unit="kf"):
        data = encode(frame)
        (out / f"{rec.robot_id}_{frame.stamp:.6f}.fmf").write_bytes(data)
        total += len(data)
    print(
        f"{n} keyframes of {len(rec)} frames -> {out} "
        f"({total / max(n, 1) / 1024:.1f} KiB per frame)"
    )
    return 0


def cmd_vocab_train(args: argparse.Namespace) -> int:
    """Train the GIST codebook and SIFT words (thesis Algorithm 1)."""
    from shared.training import collect_images, train_from_images

    paths = collect_images(args.inputs, stride=args.stride)
    vocab = train_from_images(
        paths,
        n_gist_clusters=args.gist_clusters,
        n_words=args.words,
        seed=args.seed,
        progress=lambda it: tqdm(it, total=len(paths), desc="describe", unit="img"),
        source=args.source or ", ".join(str(i) for i in args.inputs),
    )
    vocab.save(args.output)
    print(
        f"vocabulary {vocab.vocab_id}: {len(vocab.gist_centroids)} GIST clusters, "
        f"{vocab.n_words} words from {len(paths)} images -> {args.output}"
    )
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    """Run one service in the foreground until SIGTERM/SIGINT."""
    import uvicorn

    from services.common import header_timeout_protocol

    if args.service == "place-db":
        from services.place_db.config import Settings
        from services.place_db.main import create_app
        from shared.placedb import check_database_file

        overrides = {"data_dir": Path(args.data_dir)} if args.data_dir else {}
        settings = Settings(**overrides)
        check_database_file(settings.db_path)  # a damaged file: one line, exit 1
        app = create_app(settings)
    else:
        from services.aligner.config import Settings as AlignerSettings
        from services.aligner.main import create_app as create_aligner

        app = create_aligner(AlignerSettings())
    port = args.port or (8100 if args.service == "place-db" else 8200)
    from services.common import auth_summary

    log.warning(
        "fleetmap %s %s listening on http://%s:%d (%s)",
        args.service,
        _version(),
        args.host,
        port,
        auth_summary(app.state.settings),
    )
    uvicorn.run(
        app,
        host=args.host,
        port=port,
        log_level="info" if args.verbose else "warning",
        timeout_graceful_shutdown=30,
        # our middleware logs each request (path without query string, sanitised id);
        # uvicorn's access line would log a token sent as ?token=... verbatim
        access_log=False,
        http=header_timeout_protocol(),
    )
    return 0


def ingest_robot(robot_arg: str, client, args: argparse.Namespace, vocab) -> tuple[str, int]:
    """Extract a robot folder's keyframes and POST them; returns (robot id, keyframes)."""
    from shared.dataset import parse_robot_arg, read_recording
    from shared.extract import FrameExtractor, extract_recording, keyframe_indices

    name, robot_dir = parse_robot_arg(robot_arg)
    rec = read_recording(robot_dir, name, _intrinsics(args, robot_dir), topics=_topics(args))
    n = len(keyframe_indices(rec, _policy(args)))
    frames = extract_recording(rec, FrameExtractor(vocab), _policy(args))
    for frame in tqdm(
        frames,
        total=n,
        desc=f"ingest {rec.robot_id}",
        unit="kf",
        disable=getattr(args, "quiet", False),
    ):
        client.add_keyframe(frame)
    return rec.robot_id, n


def _checked_vocabulary(client, path):
    """The vocabulary to extract with: the service's must be the same."""
    from shared.errors import BadVocabulary
    from shared.vocabulary import load_vocabulary

    vocab = load_vocabulary(path)
    served = client.vocabulary()["vocab_id"]
    if served != vocab.vocab_id:
        raise BadVocabulary(
            f"The place database uses vocabulary {served}, this CLI loaded "
            f"{vocab.vocab_id}: pass the same file with --vocab"
        )
    return vocab


def cmd_ingest(args: argparse.Namespace) -> int:
    """Select keyframes of robot folders, compute their frame structures and POST them."""
    from shared.client import PlaceDBClient

    with PlaceDBClient(args.place_db, token=args.token) as client:
        vocab = _checked_vocabulary(client, args.vocab)
        for robot in args.robots:
            rid, n = ingest_robot(robot, client, args, vocab)
            print(f"{rid}: {n} keyframes ingested")
    return 0


def cmd_overlaps(args: argparse.Namespace) -> int:
    """Verified keyframe pairs between two robots."""
    import json

    from shared.client import PlaceDBClient

    with PlaceDBClient(args.place_db, token=args.token) as client:
        pairs = client.overlaps(args.robot_a, args.robot_b, wait=args.wait)
    items = [
        {
            "robot_a": p["robot_a"],
            "stamp_a": p["stamp_a"],
            "robot_b": p["robot_b"],
            "stamp_b": p["stamp_b"],
            "inliers": p["inliers"],
            "keyframe_a": p["keyframe_a"],
            "keyframe_b": p["keyframe_b"],
        }
        for p in pairs
    ]
    if args.json:
        print(json.dumps({"overlaps": items}, indent=2))
    else:
        print(f"{len(items)} verified pairs between {args.robot_a} and {args.robot_b}")
        for it in items:
            print(f"  {it['stamp_a']:.6f} <-> {it['stamp_b']:.6f}  {it['inliers']} inliers")
    return 0


def cmd_align(args: argparse.Namespace) -> int:
    """Align robot B's map to robot A's from their verified overlaps."""
    import json

    from shared.client import AlignerClient, PlaceDBClient
    from shared.extract import keyframe_indices
    from shared.pairs import load_view, select_views

    rec_a, rec_b = _read_robots(args, [args.robot_a, args.robot_b])
    with PlaceDBClient(args.place_db, token=args.token) as db:
        overlaps = db.overlaps(rec_a.robot_id, rec_b.robot_id, wait=args.wait)
    ia, ib = select_views(
        overlaps,
        rec_a,
        rec_b,
        keyframe_indices(rec_a, _policy(args)),
        keyframe_indices(rec_b, _policy(args)),
        args.max_views,
    )
    if not ia:
        out = {
            "merged": False,
            "reason": f"no verified overlap between {rec_a.robot_id} and {rec_b.robot_id}",
        }
    else:
        va, vb = [load_view(rec_a, i) for i in ia], [load_view(rec_b, j) for j in ib]
        views = [(x, y) for x in va for y in vb]
        with AlignerClient(args.aligner, timeout=600, token=args.token) as aligner:
            res = aligner.align(views, method=args.method)
        out = {
            "merged": res["merged"],
            "robot_a": rec_a.robot_id,
            "robot_b": rec_b.robot_id,
            "views": [len(va), len(vb)],
            **res,
        }
        if not res["merged"]:
            out.pop("transform", None)
    if args.json:
        print(json.dumps(out, indent=2))
    elif out["merged"]:
        print(
            f"merged {rec_b.robot_id} into {rec_a.robot_id} ({out['method']}, "
            f"{out['inliers']} inliers, held-out {out['holdout_residual_m']:.3f} m):"
        )
        for row in out["transform"]:
            print("  " + " ".join(f"{v:10.5f}" for v in row))
    else:
        print(f"not merged: {out['reason']}")
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    """The main job: N robot folders in, one global map and report out."""
    from services.merge import run_merge
    from shared.errors import BadInput
    from shared.pictures import n_cascade

    recs = _read_robots(args, args.robots)
    ids = [r.robot_id for r in recs]
    if len(set(ids)) != len(ids):
        raise BadInput(f"Robot ids must differ, got {ids}: name them with NAME=DIR")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out} exists and is not a folder")
    report = run_merge(
        recs,
        out,
        _policy(args),
        args.vocab,
        args.place_db,
        args.aligner,
        max_views=args.max_views,
        voxel=args.voxel,
        quiet=args.quiet,
        token=args.token,
        pcd=args.pcd,
    )
    merged = [r for r in ids if r not in report["unmerged"]]
    print(
        f"merged {len(merged)} of {len(ids)} robots into {report['reference']}'s frame "
        f"({n_cascade(report)} verified overlaps, "
        f"{len(report['overlaps']) - n_cascade(report)} more co-visible once aligned, "
        f"{report['timing_s']['total']:.1f} s)"
    )
    if report["unmerged"]:
        print(f"unmerged (no trustworthy overlap): {', '.join(report['unmerged'])}")
    print(f"results: {out / 'report.json'}, {out / 'merged.ply'}, {out / 'overview.png'}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """A synthetic fleet recording with the true transforms beside it."""
    from shared.simulate import simulate_fleet

    out = Path(args.out)
    if args.robots < 1:
        from shared.errors import BadInput

        raise BadInput(f"--robots must be at least 1, got {args.robots}")
    simulate_fleet(
        out, args.robots, args.frames, args.seed, progress=lambda it, **kw: tqdm(it, **kw)
    )
    print(
        f"{args.robots} robots x {args.frames} frames -> {out} (true transforms: "
        f"{out / 'T_true.json'})"
    )
    return 0


EPILOG = """examples:
  fleetmap merge A=robots/alpha B=robots/bravo -o out/      # services started in-process
  fleetmap serve place-db --port 8100 --data-dir /var/lib/fleetmap
  fleetmap ingest robots/alpha --place-db http://host:8100
  fleetmap overlaps alpha bravo --place-db http://host:8100 --json

environment: FLEETMAP_PLACE_DB_URL, FLEETMAP_ALIGNER_URL (default service URLs),
FLEETMAP_TOKEN (bearer token), FLEETMAP_LOG_FORMAT=json.
exit status: 0 done, 1 an error while running (bad data, unreachable service), 2 a usage
mistake, 130 interrupted."""


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fleetmap")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _url_arg(p: argparse.ArgumentParser, flag: str, env: str, required: bool, what: str) -> None:
    default = os.environ.get(env) or None
    p.add_argument(
        flag,
        metavar="URL",
        default=default,
        required=required and default is None,
        help=f"{what} (default: ${env}{'' if required else ', else one started in-process'})",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fleetmap",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"fleetmap {_version()}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    parser.add_argument(
        "-q", "--quiet", action="store_true", help="no progress bars (errors still shown)"
    )
    parser.add_argument(
        "--token",
        default=os.environ.get("FLEETMAP_TOKEN"),
        help="bearer token for the services (default: $FLEETMAP_TOKEN)",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("extract", help="frame structures of a robot folder's keyframes")
    p.add_argument("robot", metavar="[NAME=]ROBOT_DIR")
    p.add_argument("-o", "--out", "--output", dest="output", required=True, metavar="FRAMES_DIR")
    p.add_argument("--vocab", help="vocabulary file (default: the shipped one)")
    _add_camera_args(p)
    _add_keyframe_args(p)
    _add_bag_args(p)
    p.set_defaults(func=cmd_extract)

    vocab = sub.add_parser("vocab", help="vocabularies").add_subparsers(
        dest="vocab_cmd", required=True
    )
    p = vocab.add_parser("train", help="train a vocabulary (thesis Algorithm 1)")
    p.add_argument("inputs", nargs="+", metavar="IMAGES_OR_ROBOT_DIRS")
    p.add_argument("-o", "--out", "--output", dest="output", required=True, metavar="FILE")
    p.add_argument("--gist-clusters", type=int, default=8, help="GIST codebook size")
    p.add_argument("--words", type=int, default=500, help="SIFT visual words")
    p.add_argument("--stride", type=int, default=1, help="every n-th image of a folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--source", default="", help="text recorded as the training source")
    p.set_defaults(func=cmd_vocab_train)

    p = sub.add_parser("serve", help="run a service in the foreground")
    p.add_argument("service", choices=["place-db", "aligner"])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=None, help="default 8100 / 8200")
    p.add_argument("--data-dir", help="place database storage (default: per-user data folder)")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("ingest", help="extract robot folders and POST them to the place db")
    p.add_argument("robots", nargs="+", metavar="[NAME=]ROBOT_DIR")
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", True, "place database")
    p.add_argument("--vocab", help="vocabulary file (must be the service's)")
    _add_camera_args(p)
    _add_keyframe_args(p)
    _add_bag_args(p)
    p.set_defaults(func=cmd_ingest)

    p = sub.add_parser("overlaps", help="verified keyframe pairs between two robots")
    p.add_argument("robot_a")
    p.add_argument("robot_b")
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", True, "place database")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument(
        "--wait",
        type=float,
        default=120.0,
        help="seconds to wait for queued overlap detection (default 120)",
    )
    p.set_defaults(func=cmd_overlaps)

    p = sub.add_parser("align", help="fit robot B's map frame into robot A's")
    p.add_argument("robot_a", metavar="[NAME=]ROBOT_DIR_A")
    p.add_argument("robot_b", metavar="[NAME=]ROBOT_DIR_B")
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", True, "place database")
    _url_arg(p, "--aligner", "FLEETMAP_ALIGNER_URL", True, "aligner")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument(
        "--method",
        default="default",
        choices=["default", "rigid", "similarity", "affine", "mlp", "icp", "fpfh"],
    )
    p.add_argument("--max-views", type=int, default=12, help="views per robot sent to the aligner")
    p.add_argument("--wait", type=float, default=120.0, help="seconds to wait for overlaps")
    _add_camera_args(p)
    _add_keyframe_args(p)
    _add_bag_args(p)
    p.set_defaults(func=cmd_align)

    p = sub.add_parser("merge", help="the main job: merge N robots' maps into one")
    p.add_argument("robots", nargs="+", metavar="[NAME=]ROBOT_DIR")
    p.add_argument("-o", "--out", "--output", dest="out", required=True, metavar="OUT_DIR")
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", False, "place database")
    _url_arg(p, "--aligner", "FLEETMAP_ALIGNER_URL", False, "aligner")
    p.add_argument("--vocab", help="vocabulary file (must be the place database's)")
    p.add_argument("--max-views", type=int, default=12, help="views per robot sent to the aligner")
    p.add_argument("--pcd", action="store_true", help="also write merged.pcd (PCL's format)")
    p.add_argument(
        "--voxel", type=float, default=0.03, metavar="M", help="merged map voxel size (0.03 m)"
    )
    _add_camera_args(p)
    _add_keyframe_args(p)
    _add_bag_args(p)
    p.set_defaults(func=cmd_merge)

    p = sub.add_parser("convert", help="write a ROS bag robot out as a TUM folder")
    p.add_argument("bag", metavar="BAG", help="a ROS 1 .bag or a ROS 2 bag folder")
    p.add_argument("-o", "--out", "--output", dest="output", required=True, metavar="DIR")
    _add_bag_args(p)
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("simulate", help="render a synthetic fleet recording (TUM layout)")
    p.add_argument("out", metavar="OUT_DIR")
    p.add_argument("--robots", type=int, default=3, help="how many robots")
    p.add_argument("--frames", type=int, default=30, help="frames per robot")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.set_defaults(func=cmd_simulate)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if os.environ.get("FLEETMAP_LOG_FORMAT", "").lower() == "json":
        from services.common import JsonFormatter

        for handler in logging.getLogger().handlers:
            handler.setFormatter(JsonFormatter())
    try:
        return args.func(args)
    except FleetmapError as exc:
        print(f"fleetmap: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:  # a path we cannot write or read: one line, not a traceback
        where = f": {exc.filename}" if exc.filename else ""
        print(f"fleetmap: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("fleetmap: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
