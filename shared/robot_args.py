"""Robots as the command line names them: `[NAME=]DIR` arguments, each recording once."""

from __future__ import annotations

import logging
from pathlib import Path

from fleetmap.camera import TUM_FR1, Intrinsics
from fleetmap.dataset import Recording, default_robot_id, read_recording
from fleetmap.errors import BadInput, BadRobotData
from fleetmap.frame import check_robot_id
from fleetmap.view import check_intrinsics

log = logging.getLogger(__name__)


def parse_robot_arg(arg: str) -> tuple[str | None, Path]:
    """'NAME=DIR' or 'DIR' as (name or None, path); NAME a robot id, DIR given."""
    if "=" in arg and not _exists(arg):
        name, _, path = arg.partition("=")
        if name and not path:  # 'A=' read the working folder
            raise BadRobotData(f"{arg}: no robot folder after '='")
        if name:  # a 300-letter name failed as "File name too long"
            return check_robot_id(name), Path(path)
    return None, Path(arg)


def read_robot(arg: str, intrinsics_for, **kwargs) -> Recording:
    """The recording a `[NAME=]DIR` argument names, read with `intrinsics_for(DIR)` (None:
    the folder's own camera) and `read_recording`'s other keyword arguments."""
    name, robot_dir = parse_robot_arg(arg)
    rec = read_recording(robot_dir, name, intrinsics_for(robot_dir), **kwargs)
    if name is None:  # the folder's name: refused only where the first keyframe was encoded
        try:
            check_robot_id(rec.robot_id)
        except BadInput as exc:
            raise BadInput(f"{exc} (the folder's name): give one, as NAME={robot_dir}") from None
    return rec


def _exists(path: str) -> bool:
    try:
        return Path(path).exists()
    except OSError:  # a name too long for the file system: no such file
        return False


def check_distinct(recs: list[Recording]) -> list[Recording]:
    """`recs`, each recording once: one folder under two names merged with itself, unsaid."""
    where = [Path(r.source or r.root).resolve() for r in recs]
    for k, w in enumerate(where):
        if w in where[:k]:
            names = f"{recs[where.index(w)].robot_id} and {recs[k].robot_id}"
            raise BadRobotData(f"{w} is given twice ({names}): one recording is one robot")
    return recs


def check_topics(recs: list[Recording], topics) -> list[Recording]:
    """`recs`, where bag topics (`bags.BagTopics`) were given only if one of them is a ROS
    bag: `--rgb-topic` on folders alone was taken and ignored, unsaid (an outside tester's
    review). In a fleet of bags and folders the topics choose the bags' messages."""
    given = [f"--{k}-topic" for k in ("rgb", "depth", "info", "pose") if getattr(topics, k)]
    if given and not any(r.source for r in recs):
        raise BadInput(
            f"{' '.join(given)}: no robot given is a ROS bag (they choose a bag's topics)"
        )
    return recs


def distinct_ids(recs: list[Recording]) -> list[Recording]:
    """`recs`, whose robot ids differ (a fleet job's: `merge`, `stream`)."""
    check_ids([r.robot_id for r in recs])
    return recs


def arg_robot_id(arg: str) -> str:
    """The robot id a `[NAME=]DIR` argument gives, before its folder is read (as
    `read_recording` names it: NAME, else `dataset.default_robot_id`)."""
    name, path = parse_robot_arg(arg)
    return name or default_robot_id(path)


def check_ids(ids: list[str]) -> None:
    """Robot ids of one command: each once (`ingest x=A x=B` stored B under A's name)."""
    if len(set(ids)) != len(ids):
        raise BadInput(f"Robot ids must differ, got {ids}: name them with NAME=DIR")


_FOUR = {"fx", "fy", "cx", "cy"}


def overridden(root: Path, flags: dict, topics=None) -> Intrinsics:
    """The intrinsics of the robot at `root` with `flags` (the CLI's fx, fy, cx, cy,
    depth_scale) over camera.json's, a bag's, or the TUM fr1 defaults', at the files' own
    size. Checked as camera.json is (`view.check_intrinsics`). Where the flags change the
    robot's own camera (camera.json, a bag's), it is said: the flags apply to every robot of
    the command, and in a fleet of mixed cameras one robot's fix is the others' error (an
    outside tester's review)."""
    from fleetmap.bags import is_bag

    bare = not is_bag(root) and not (Path(root) / "camera.json").exists()  # the defaults'
    stand_in = bare and _FOUR <= set(flags)  # not the defaults' camera: said only if not
    rec = read_recording(root, intrinsics=TUM_FR1 if stand_in else None, topics=topics)
    own = (rec.file_intrinsics or rec.intrinsics).to_dict()
    K = Intrinsics.from_dict({**own, **flags})
    check_intrinsics(K, K.width, K.height, "--fx --fy --cx --cy")
    if bare and not stand_in:  # the defaults' warning listed what these flags replace
        log.warning("%s: %s taken over those defaults", root, _as_flags(flags, list(flags)))
    changed = [k for k, v in flags.items() if not bare and own[k] != v]
    if changed:
        log.warning(
            "%s: %s replace its own camera's %s (the camera flags apply to every robot of the "
            "command: give a robot of another camera its own camera.json instead)", root,
            _as_flags(flags, changed),
            ", ".join(f"{k} {own[k]:g}" for k in changed),
        )  # fmt: skip
    return K


def _as_flags(flags: dict, keys: list) -> str:
    """The camera flags `keys` of `flags` as they were given: "--fx 436.5 --depth-scale 1000"."""
    return " ".join(f"--{k.replace('_', '-')} {flags[k]:g}" for k in keys)
