"""`fleetmap`: the command line for robots' data, the services and the main job."""

from __future__ import annotations

import argparse
import logging
import os
import sys

from fleetmap.align.methods import METHODS
from fleetmap.errors import FleetmapError
from fleetmap.fleet.types import DEFAULT_MERGE, MIN_VOXEL_M
from fleetmap.services import commands

KF = DEFAULT_MERGE.keyframes  # the CLI's defaults are the stages' (`fleetmap.fleet.types`)

log = logging.getLogger("fleetmap")


def _add_camera_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("camera overrides (default: camera.json, else TUM fr1)")
    for name in ("fx", "fy", "cx", "cy"):  # plausibility for the image size: where read
        g.add_argument(f"--{name}", type=_number(f"{name} (pixels, above 0)", 0, above=True))
    scale = _number("depth scale (units per metre, above 0)", 0, above=True)
    g.add_argument("--depth-scale", type=scale, help="depth units per metre (TUM: 5000)")


def _add_keyframe_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("keyframe selection")
    g.add_argument(
        "--kf-translation",
        type=_threshold,
        default=KF.min_translation_m,
        metavar="M",
        help="new keyframe after moving this far (default %(default)g m)",
    )
    g.add_argument(
        "--kf-rotation",
        type=_threshold,
        default=KF.min_rotation_deg,
        metavar="DEG",
        help="new keyframe after turning this much (default %(default)g deg)",
    )
    g.add_argument(
        "--kf-interval",
        type=_threshold,
        default=KF.max_interval_s,
        metavar="S",
        help="new keyframe after this long at the latest (default %(default)g s)",
    )


def _add_bag_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("ROS bags (.bag, or a ROS 2 bag folder): topics where ambiguous")
    g.add_argument("--rgb-topic", help="sensor_msgs/Image colour topic")
    g.add_argument("--depth-topic", help="sensor_msgs/Image depth topic (16UC1 mm, 32FC1 m)")
    g.add_argument("--info-topic", help="sensor_msgs/CameraInfo topic")
    g.add_argument("--pose-topic", help="PoseStamped or Odometry: camera in the map frame")


def _add_max_views(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--max-views",
        type=_positive_count,
        default=DEFAULT_MERGE.views.max_views,
        help="views per robot sent to the aligner (default %(default)s; an aligner takes "
        "32 at most unless its FLEETMAP_ALIGNER_MAX_VIEWS says more)",
    )


def _add_voxel(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--voxel",
        type=_voxel_m,
        default=DEFAULT_MERGE.voxel_m,
        metavar="M",
        help="merged map voxel size (default %(default)g m)",
    )


def _add_robot_args(p: argparse.ArgumentParser) -> None:
    """How robot folders are read: camera, keyframe selection, bag topics."""
    _add_camera_args(p)
    _add_keyframe_args(p)
    _add_bag_args(p)


EPILOG = """examples:
  fleetmap merge A=robots/alpha B=robots/bravo -o out/      # services started in-process
  fleetmap serve place-db --port 8100 --data-dir /var/lib/fleetmap
  fleetmap ingest robots/alpha --place-db http://host:8100
  fleetmap overlaps alpha bravo --place-db http://host:8100 --json

environment: FLEETMAP_PLACE_DB_URL, FLEETMAP_ALIGNER_URL (default service URLs),
FLEETMAP_TOKEN (bearer token), FLEETMAP_LOG_FORMAT=json.
exit status: 0 done, 1 an error while running (bad data, unreachable service), 2 a usage
mistake, 130 interrupted."""


def _number(
    name: str,
    low: float,
    *,
    above: bool,
    finite: bool = True,
    integer: bool = False,
    high: float = float("inf"),
):
    """An argparse type: a number at least `low` (`above`: more than `low`) and at most
    `high`, never NaN, finite where `finite`; argparse turns the ValueError into a usage
    error naming it."""

    def parse(text: str):
        x = int(text) if integer else float(text)
        ok = (x > low if above else x >= low) and x == x and (not finite or abs(x) != float("inf"))
        ok = ok and x <= high
        if not ok:
            raise ValueError(text)
        return x

    parse.__name__ = name
    return parse


_voxel_m = _number(f"voxel (metres, {MIN_VOXEL_M} or more)", MIN_VOXEL_M, above=False)
_positive_count = _number("count (a whole number of 1 or more)", 0, above=True, integer=True)
#: waits: up to a day (1e12 s overflowed the clock: a traceback)
_seconds = _number("seconds (0 to 86400)", 0, above=False, high=86400)
_threshold = _number("threshold (0 or more; inf: never)", 0, above=False, finite=False)
_port = _number("port (1-65535)", 0, above=True, integer=True, high=65535)
_speed = _number("speed (0 or more)", 0, above=False)
_seed = _number("seed (a whole number from 0 to 2147483647)", -1, above=True, integer=True,
                high=2**31 - 1)  # fmt: skip


def _folder(text: str) -> str:
    """An argparse type: a folder's name, not empty (Path("") is the working folder: a merge
    wrote its outputs there)."""
    if not text.strip():
        raise ValueError(text)
    return text


_folder.__name__ = "folder name (not empty)"


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
    parser.add_argument("--version", action="version", version=f"fleetmap {commands.version()}")
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
    for add in (_data_commands, _service_commands, _pair_commands, _merge_command, _live_commands):
        add(sub)
    return parser


def _data_commands(sub) -> None:
    """Commands on robots' data alone: extract, vocab train, convert, simulate."""
    p = sub.add_parser("extract", help="frame structures of a robot folder's keyframes")
    p.add_argument("robot", metavar="[NAME=]ROBOT_DIR")
    p.add_argument(
        "-o", "--out", "--output", dest="output", required=True, metavar="FRAMES_DIR", type=_folder
    )
    p.add_argument("--vocab", help="vocabulary file (default: the shipped one)")
    _add_robot_args(p)
    p.set_defaults(func=commands.cmd_extract)

    vocab = sub.add_parser("vocab", help="vocabularies").add_subparsers(
        dest="vocab_cmd", required=True
    )
    p = vocab.add_parser("train", help="train a vocabulary (thesis Algorithm 1)")
    p.add_argument("inputs", nargs="+", metavar="IMAGES_OR_ROBOT_DIRS")
    p.add_argument("-o", "--out", "--output", dest="output", required=True, metavar="FILE")
    p.add_argument("--gist-clusters", type=_positive_count, default=8, help="GIST codebook size")
    p.add_argument("--words", type=_positive_count, default=500, help="SIFT visual words")
    p.add_argument("--stride", type=_positive_count, default=1, help="every n-th image of a folder")
    p.add_argument("--seed", type=_seed, default=0)
    p.add_argument("--source", default="", help="text recorded as the training source")
    p.set_defaults(func=commands.cmd_vocab_train)

    p = sub.add_parser("convert", help="write a ROS bag robot out as a TUM folder")
    p.add_argument("bag", metavar="BAG", help="a ROS 1 .bag or a ROS 2 bag folder")
    p.add_argument(
        "-o", "--out", "--output", dest="output", required=True, metavar="DIR", type=_folder
    )
    _add_bag_args(p)
    p.set_defaults(func=commands.cmd_convert)

    p = sub.add_parser("simulate", help="render a synthetic fleet recording (TUM layout)")
    p.add_argument("out", metavar="OUT_DIR", type=_folder)
    p.add_argument("--robots", type=_positive_count, default=3, help="how many robots")
    p.add_argument("--frames", type=_positive_count, default=30, help="frames per robot")
    p.add_argument("--seed", type=_seed, default=0, help="random seed")
    p.set_defaults(func=commands.cmd_simulate)


def _service_commands(sub) -> None:
    """serve, and the place database's operator commands: ingest, overlaps."""
    p = sub.add_parser("serve", help="run a service in the foreground")
    p.add_argument("service", choices=["place-db", "aligner"])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=_port, default=None, help="default 8100 / 8200")
    p.add_argument("--data-dir", help="place database storage (default: per-user data folder)")
    p.add_argument(
        "--database",
        metavar="URL",
        help="place-db on PostgreSQL: postgresql://USER[:PASS]@HOST:PORT/DB, shared by any "
        "number of replicas (default: $FLEETMAP_PLACE_DB_DATABASE, else SQLite in --data-dir)",
    )
    p.add_argument(
        "--aligner",
        metavar="URL",
        help="place-db: merge robots live through this aligner as their overlaps appear "
        "(GET /map; default: $FLEETMAP_PLACE_DB_ALIGNER, else no merge worker)",
    )
    p.set_defaults(func=commands.cmd_serve)

    p = sub.add_parser("ingest", help="extract robot folders and POST them to the place db")
    p.add_argument("robots", nargs="+", metavar="[NAME=]ROBOT_DIR")
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", True, "place database")
    p.add_argument("--vocab", help="vocabulary file (must be the service's)")
    _add_robot_args(p)
    p.set_defaults(func=commands.cmd_ingest)

    p = sub.add_parser("overlaps", help="verified keyframe pairs between two robots")
    p.add_argument("robot_a")
    p.add_argument("robot_b")
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", True, "place database")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument(
        "--wait",
        type=_seconds,
        default=120.0,
        help="seconds to wait for queued overlap detection (default 120)",
    )
    p.set_defaults(func=commands.cmd_overlaps)


def _pair_commands(sub) -> None:
    """align: one robot pair through both services."""
    p = sub.add_parser(
        "align",
        help="fit robot B's map frame into robot A's",
        description="One robot pair through running services: both robots must be in the "
        "place database already (`fleetmap ingest` each folder first). `fleetmap merge` does "
        "all of it, with services of its own where none are given.",
        epilog="methods:\n" + "\n".join(f"  {k}: {m.description}" for k, m in METHODS.items()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("robot_a", metavar="[NAME=]ROBOT_DIR_A", help="the robot whose frame is kept")
    p.add_argument("robot_b", metavar="[NAME=]ROBOT_DIR_B", help="the robot placed in it")
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", True, "place database")
    _url_arg(p, "--aligner", "FLEETMAP_ALIGNER_URL", True, "aligner")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument(
        "--method",
        default="default",
        choices=list(METHODS),
        help="alignment method (default: the gated fit `merge` uses; the others, one estimator "
        "without the quality gate for comparison, below)",
    )
    _add_max_views(p)
    p.add_argument("--wait", type=_seconds, default=120.0, help="seconds to wait for overlaps")
    _add_robot_args(p)
    p.set_defaults(func=commands.cmd_align)


def _merge_command(sub) -> None:
    p = sub.add_parser("merge", help="the main job: merge N robots' maps into one")
    p.add_argument("robots", nargs="+", metavar="[NAME=]ROBOT_DIR")
    p.add_argument(
        "-o", "--out", "--output", dest="out", required=True, metavar="OUT_DIR", type=_folder
    )
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", False, "place database")
    _url_arg(p, "--aligner", "FLEETMAP_ALIGNER_URL", False, "aligner")
    p.add_argument("--vocab", help="vocabulary file (must be the place database's)")
    _add_max_views(p)
    p.add_argument("--pcd", action="store_true", help="also write merged.pcd (PCL's format)")
    p.add_argument(
        "--correct-drift",
        action=argparse.BooleanOptionalAction,
        default=DEFAULT_MERGE.correct_drift,
        help="one pose graph over every robot's keyframes corrects maps that bend (drift); "
        "on by default, --no-correct-drift keeps every map rigid and skips the loop-closure "
        "search (a few seconds)",
    )
    _add_voxel(p)
    _add_robot_args(p)
    p.set_defaults(func=commands.cmd_merge)


def _live_commands(sub) -> None:
    """stream and map: the live fleet map (CONTRACT section 6)."""
    from fleetmap.services import live

    p = sub.add_parser(
        "stream",
        help="replay robot recordings into a place database as robots would stream them",
        description="Every robot at once, keyframes in time order with their RGB-D views, at "
        "--speed times recording speed. With `fleetmap serve place-db --aligner URL` the "
        "place database merges the robots as their overlaps appear.",
    )
    p.add_argument("robots", nargs="+", metavar="[NAME=]ROBOT_DIR")
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", True, "place database")
    p.add_argument(
        "--speed",
        type=_speed,
        default=1.0,
        metavar="X",
        help="times recording speed (default 1; 0: as fast as possible)",
    )
    p.add_argument(
        "--nice",
        type=int,
        default=10,
        metavar="N",
        help="run the replay (extraction, upload) at this niceness, so that services on "
        "the same machine go first, as beside robots that extract on board (default 10)",
    )
    p.add_argument("--vocab", help="vocabulary file (must be the service's)")
    _add_robot_args(p)
    p.set_defaults(func=live.cmd_stream)

    p = sub.add_parser(
        "map",
        help="write the live map of a place database (what merge writes)",
        description="report.json, merged.ply, overview.png, overlap_matrix.png, "
        "pose_graph.g2o and trajectories/ (keyframe poses) from GET /map.",
    )
    _url_arg(p, "--place-db", "FLEETMAP_PLACE_DB_URL", True, "place database")
    p.add_argument(
        "-o", "--out", "--output", dest="out", required=True, metavar="OUT_DIR", type=_folder
    )
    _add_voxel(p)
    p.set_defaults(func=live.cmd_map)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if os.environ.get("FLEETMAP_LOG_FORMAT", "").lower() == "json":
        from fleetmap.services.common import JsonFormatter

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
