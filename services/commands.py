"""The CLI's commands: each takes the parsed arguments and returns the exit status."""

from __future__ import annotations

import argparse
import logging
import shutil
from pathlib import Path

from tqdm import tqdm

from fleetmap.camera import Intrinsics
from fleetmap.errors import BadInput, BadRobotData, UnknownRobot
from fleetmap.lazy import require

log = logging.getLogger("fleetmap")


def _topics(args: argparse.Namespace):
    from fleetmap.bags import BagTopics

    return BagTopics(*(getattr(args, f"{k}_topic", None) for k in ("rgb", "depth", "info", "pose")))


def cmd_convert(args: argparse.Namespace) -> int:
    """A ROS bag robot written out as a TUM folder."""
    from fleetmap.bags import bag_to_tum, is_bag
    from fleetmap.dataset import read_recording

    src, out = Path(args.bag), Path(args.output)
    if not is_bag(src):
        raise BadRobotData(f"{src}: not a ROS bag (.bag, or a folder with metadata.yaml)")
    if out.exists():
        raise BadInput(f"{out} exists: give a new folder")
    try:
        bag_to_tum(src, out, _topics(args))
        rec = read_recording(out)
    except BaseException:  # a failed convert left its folder, which refused the retry
        shutil.rmtree(out, ignore_errors=True)
        raise
    print(f"{len(rec)} RGB-D frames with poses -> {out}")
    return 0


def _intrinsics(args: argparse.Namespace, robot_dir: Path) -> Intrinsics | None:
    keys = ("fx", "fy", "cx", "cy", "depth_scale")
    overrides = {k: getattr(args, k) for k in keys if getattr(args, k, None) is not None}
    if not overrides:
        return None
    from fleetmap.robot_args import overridden

    return overridden(robot_dir, overrides, _topics(args))


def _read_robots(args: argparse.Namespace, robot_args: list[str]) -> list:
    """Recordings with depth and poses for [NAME=]DIR arguments."""
    from fleetmap.robot_args import check_distinct, check_topics, read_robot

    def camera(robot_dir):
        return _intrinsics(args, robot_dir)

    kw = {"require_depth": True, "require_poses": True, "topics": _topics(args)}
    return check_topics(
        check_distinct([read_robot(arg, camera, **kw) for arg in robot_args]), kw["topics"]
    )


def _policy(args: argparse.Namespace):
    from fleetmap.keyframes import KeyframePolicy

    return KeyframePolicy(args.kf_translation, args.kf_rotation, args.kf_interval)


def _merge_params(args: argparse.Namespace):
    """`merge`'s flags as its stage parameters (`fleetmap.fleet.types.MergeParams`)."""
    from fleetmap.fleet.types import MergeParams, ViewParams

    return MergeParams(
        keyframes=_policy(args),
        views=ViewParams(max_views=args.max_views),
        voxel_m=args.voxel,
        pcd=args.pcd,
        correct_drift=args.correct_drift,
    )


def cmd_extract(args: argparse.Namespace) -> int:
    """Write one encoded frame structure per keyframe of a robot folder."""
    from fleetmap.extract import FrameExtractor, extract_recording, keyframe_indices
    from fleetmap.frame import encode
    from fleetmap.robot_args import check_topics, read_robot
    from fleetmap.vocabulary import load_vocabulary

    rec = read_robot(args.robot, lambda d: _intrinsics(args, d), topics=_topics(args))
    check_topics([rec], _topics(args))
    extractor = FrameExtractor(load_vocabulary(args.vocab))
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    n = len(keyframe_indices(rec, _policy(args)))
    total, written = 0, []
    frames = extract_recording(rec, extractor, _policy(args))
    bar = tqdm(frames, total=n, desc=f"extract {rec.robot_id}", unit="kf", disable=args.quiet)
    try:
        for frame in bar:
            data, path = encode(frame), out / f"{rec.robot_id}_{frame.stamp:.6f}.fmf"
            if not path.exists():  # a file of an earlier run stays
                written.append(path)
            total += path.write_bytes(data)
    except BaseException:  # a frame that cannot be read: no half a robot left behind
        for path in written:
            path.unlink(missing_ok=True)
        raise
    per = total / max(n, 1) / 1024
    print(f"{n} keyframes of {len(rec)} frames -> {out} ({per:.1f} KiB per frame)")
    return 0


def cmd_vocab_train(args: argparse.Namespace) -> int:
    """Train the GIST codebook and SIFT words (thesis Algorithm 1)."""
    require("fleetmap vocab train", ("faiss",))
    from fleetmap.services.outputs import prepare_file
    from fleetmap.training import collect_images, train_from_images

    prepare_file(Path(args.output))
    paths = collect_images(args.inputs, stride=args.stride)
    vocab = train_from_images(
        paths,
        n_gist_clusters=args.gist_clusters,
        n_words=args.words,
        seed=args.seed,
        progress=lambda it: tqdm(
            it, total=len(paths), desc="describe", unit="img", disable=args.quiet
        ),
        source=args.source or ", ".join(str(i) for i in args.inputs),
    )
    vocab.save(args.output)
    print(
        f"vocabulary {vocab.vocab_id}: {len(vocab.gist_centroids)} GIST clusters, "
        f"{vocab.n_words} words from {len(paths)} images -> {args.output}"
    )
    return 0


def _settings(cls, **overrides):
    """A service's settings; an unreadable environment variable is one line naming it."""
    from fleetmap.services.settings import unreadable

    try:
        return cls(**overrides)
    except Exception as exc:
        why = unreadable(exc)
        if why is None:
            raise
        raise why from None


def cmd_serve(args: argparse.Namespace) -> int:
    """Run one service in the foreground until SIGTERM/SIGINT."""
    require("fleetmap serve")
    import uvicorn

    from fleetmap.services.common import header_timeout_protocol

    if args.service == "place-db":
        from fleetmap.place import check_database_file
        from fleetmap.services.place_db.config import Settings
        from fleetmap.services.place_db.main import create_app

        overrides = {"data_dir": Path(args.data_dir)} if args.data_dir else {}
        if args.database:
            overrides["database"] = args.database
        if args.aligner:
            overrides["aligner"] = args.aligner
        settings = _settings(Settings, **overrides)
        if settings.database is None:
            settings.data_dir.mkdir(parents=True, exist_ok=True)  # cannot: one line, exit 1
            check_database_file(settings.db_path)  # damaged, or in use: one line, exit 1
        else:
            from fleetmap.place.postgres_schema import check_reachable

            check_reachable(settings.store)  # down or refused: one line, exit 1
        app = create_app(settings, announce=False)  # the start line below says it
    else:
        from fleetmap.services.aligner.config import Settings as AlignerSettings
        from fleetmap.services.aligner.main import create_app as create_aligner

        app = create_aligner(_settings(AlignerSettings), announce=False)
    port = args.port or (8100 if args.service == "place-db" else 8200)
    from fleetmap.services.common import auth_summary, check_port

    check_port(args.host, port)  # taken: one line, exit 1 (not "listening", then uvicorn's 3)

    log.warning(
        "fleetmap %s %s listening on http://%s:%d (%s)",
        args.service,
        version(),
        args.host,
        port,
        auth_summary(app.state.settings, args.host),
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
        http=header_timeout_protocol(app.state.settings.header_timeout_s),
    )
    return 0


def ingest_robot(robot_arg: str, client, args: argparse.Namespace, vocab) -> tuple[str, int]:
    """Extract a robot folder's keyframes and POST them; returns (robot id, keyframes)."""
    from fleetmap.extract import FrameExtractor, extract_recording, keyframe_indices
    from fleetmap.robot_args import read_robot

    rec = read_robot(robot_arg, lambda d: _intrinsics(args, d), topics=_topics(args))
    n = len(keyframe_indices(rec, _policy(args)))
    frames = extract_recording(rec, FrameExtractor(vocab), _policy(args))
    for frame in tqdm(
        frames,
        total=n,
        desc=f"ingest {rec.robot_id}",
        unit="kf",
        disable=args.quiet,
    ):
        client.add_keyframe(frame)
    return rec.robot_id, n


def cmd_ingest(args: argparse.Namespace) -> int:
    """Select keyframes of robot folders, compute their frame structures and POST them."""
    from fleetmap.client import PlaceDBClient
    from fleetmap.robot_args import arg_robot_id, check_ids
    from fleetmap.services.merge import checked_vocabulary

    check_ids([arg_robot_id(a) for a in args.robots])
    with PlaceDBClient(args.place_db, token=args.token) as client:
        vocab = checked_vocabulary(client, args.vocab)
        for robot in args.robots:
            rid, n = ingest_robot(robot, client, args, vocab)
            print(f"{rid}: {n} keyframes ingested")
    return 0


def cmd_overlaps(args: argparse.Namespace) -> int:
    """Verified keyframe pairs between two robots."""
    import json

    from fleetmap.client import PlaceDBClient

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

    from fleetmap.client import AlignerClient, PlaceDBClient
    from fleetmap.extract import keyframe_indices
    from fleetmap.fleet.view_choice import overlaps_to_align, pair_views

    rec_a, rec_b = _read_robots(args, [args.robot_a, args.robot_b])
    with PlaceDBClient(args.place_db, token=args.token) as db:
        try:
            overlaps = overlaps_to_align(db, rec_a.robot_id, rec_b.robot_id, wait=args.wait)
        except UnknownRobot as exc:  # the usual cause: `align` run before `ingest`
            raise UnknownRobot(f"{exc} (`fleetmap ingest` its folder first)") from None
    kfs = [keyframe_indices(r, _policy(args)) for r in (rec_a, rec_b)]
    views = pair_views(overlaps, rec_a, rec_b, *kfs, args.max_views)
    if not views:
        out = {
            "merged": False,
            "reason": f"no verified overlap between {rec_a.robot_id} and {rec_b.robot_id}",
        }
    else:
        with AlignerClient(args.aligner, timeout=600, token=args.token) as aligner:
            res = aligner.align(views, method=args.method)
        n_a, n_b = len({id(v) for v, _ in views}), len({id(v) for _, v in views})
        out = {
            "merged": res["merged"],
            "robot_a": rec_a.robot_id,
            "robot_b": rec_b.robot_id,
            "views": [n_a, n_b],
            **res,
        }
        if not res["merged"]:
            out.pop("transform", None)
    if args.json:
        print(json.dumps(out, indent=2))
    elif out["merged"]:
        print(f"merged {rec_b.robot_id} into {rec_a.robot_id} ({_fit_summary(out)}):")
        for row in out["transform"]:
            print("  " + " ".join(f"{v:10.5f}" for v in row))
    else:
        print(f"not merged: {out['reason']}")
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    """The main job: N robot folders in, one global map and report out."""
    require("fleetmap merge")
    from fleetmap.robot_args import distinct_ids
    from fleetmap.services.merge import run_merge
    from fleetmap.services.outputs import merge_summary, prepare_out

    recs = distinct_ids(_read_robots(args, args.robots))
    out = Path(args.out)
    previous = prepare_out(out, [r.robot_id for r in recs])
    report = run_merge(
        recs,
        out,
        _merge_params(args),
        args.vocab,
        args.place_db,
        args.aligner,
        quiet=args.quiet,
        token=args.token,
    )
    previous.remove_unwritten()
    print(merge_summary(report, [r.robot_id for r in recs], out))
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """A synthetic fleet recording with the true transforms beside it."""
    require("fleetmap simulate", ("scipy",))
    from fleetmap.services.outputs import prepare_empty
    from fleetmap.simulate import simulate_fleet

    out = Path(args.out)
    prepare_empty(out)
    simulate_fleet(
        out,
        args.robots,
        args.frames,
        args.seed,
        progress=lambda it, **kw: tqdm(it, disable=args.quiet, **kw),
    )
    print(
        f"{args.robots} robots x {args.frames} frames -> {out} (true transforms: "
        f"{out / 'T_true.json'})"
    )
    return 0


def version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fleetmap")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _fit_summary(fit: dict) -> str:
    """An aligner answer's "method, N inliers, held-out R m", as far as it holds them."""
    parts = [str(fit.get("method", "?"))]
    if fit.get("inliers") is not None:
        parts.append(f"{fit['inliers']} inliers")
    if fit.get("holdout_residual_m") is not None:
        parts.append(f"held-out {fit['holdout_residual_m']:.3f} m")
    return ", ".join(parts)
