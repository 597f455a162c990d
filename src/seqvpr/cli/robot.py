"""``seqvpr node`` (the localiser as a live ROS 2 participant over DDS) and ``seqvpr play`` (a bag published live, to
try the node without a robot). Both need the ``ros2`` extra (cyclonedds)."""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from typing import Any

import click

from seqvpr.cli.help import SectionedCommand, option
from seqvpr.cli.localize import localizer_options
from seqvpr.cli.options import FINITE, FLAGS, NONNEGATIVE, NONNEGATIVE_FLOAT, OUT_FILE, OUT_FOLDER, POSITIVE
from seqvpr.errors import SeqvprError, SettingError

NODE_SECTIONS = ("Input", "Method", "Map", "Localiser", "Loops", "Topics", "Output", "Compute")
DOMAIN = click.IntRange(0, 232)
LOOP_FLAGS = {"exclude": "--loop-exclude", "threshold": "--loop-threshold", "shortlist": "--loop-shortlist"}


@click.command("node", cls=SectionedCommand, sections=NODE_SECTIONS, epilog="""\b
Examples:
  seqvpr node --map maps/campus --topic /camera/image_raw/compressed --gps-topic /fix
  seqvpr node --map maps/campus --no-drop --state node.npz      # a replay: every frame; state kept on shutdown
  seqvpr node --map maps/campus --state node.npz --restore      # go on where the last run stopped
  seqvpr node --map maps/campus --loops --loop-exclude 60s      # also publish loop closures on /seqvpr/loop""")
@option("Input", "--map", "map_dir", required=True, type=click.Path(), help="A map folder (seqvpr map build).")
@localizer_options
@option("Topics", "--topic", "camera", default="/camera/image_raw", show_default=True,
        help="The camera topic: sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8, mono16) or CompressedImage.")
@option("Topics", "--image-type", type=click.Choice(["raw", "compressed"]),
        help="The camera topic's message type  [default: compressed when the topic ends in /compressed, else raw].")
@option("Topics", "--gps-topic", help="A sensor_msgs/NavSatFix topic: its distance to the estimate is in the status.")
@option("Topics", "--odom-topic", help="A nav_msgs/Odometry topic, as --gps-topic (a map in local metres).")
@option("Topics", "--domain", type=DOMAIN, help="DDS domain  [default: $ROS_DOMAIN_ID, else 0].")
@option("Localiser", "--no-drop", is_flag=True,
        help="Process every frame in order (a replay), never only the newest when behind.")
@option("Output", "--frame-id", default="map", show_default=True, help="The frame_id of the published pose.")
@option("Output", "--state", type=OUT_FILE, help="Save the localiser's state here on SIGTERM or SIGINT.")
@option("Localiser", "--restore", is_flag=True, help="Start from the state saved in --state.")
@option("Output", "--publish-images", is_flag=True,
        help="Also publish the matched map frame's thumbnail (CompressedImage) on /seqvpr/match/compressed while "
             "localised or uncertain: the map's own (map build --thumbnails), else one made once from its source "
             "image; the map's route is on /seqvpr/route (nav_msgs/Path, latched) either way.")
@option("Loops", "--loops", is_flag=True, help="Also find loop closures within the drive (its frames as described "
        "for the map, causal windows of --seq-len) and publish the accepted ones on /seqvpr/loop (DiagnosticArray, "
        "status 'seqvpr loop'); with --state, the drive so far is kept in STATE.loops.npz.")
@option("Loops", "--loop-exclude", help="The recent past a loop may not come from (30s, 200f, 50m).  [default: 30s]")
@option("Loops", "--loop-threshold", type=FINITE, help="Score a loop needs.  [default: 0.1]")
@option("Loops", "--loop-shortlist", type=NONNEGATIVE, default=0, show_default=True,
        help="Candidates from each frame's S nearest earlier frames (a growing HNSW index): a per-frame cost that "
             "stays flat over hours of driving (0: every earlier window).")
def node(**options: Any) -> None:
    """Localise a live camera topic: each frame's estimate on /seqvpr/pose (PoseWithCovarianceStamped, not while
    warming up or lost) and /seqvpr/status (DiagnosticArray); /seqvpr/reset (std_msgs/Empty) restarts it."""
    from seqvpr.cli.localize import open_localizer
    from seqvpr.localization.localizer import LocalizerSettings
    from seqvpr.ros2.dds import Bus, require_cyclonedds
    from seqvpr.ros2.camera import camera_type
    from seqvpr.ros2.messages import NAVSATFIX, ODOMETRY
    from seqvpr.ros2.node import LOOP_TOPIC, POSE_TOPIC, RESET_TOPIC, STATUS_TOPIC, LocalizerNode, NodeSettings

    require_cyclonedds()
    if options["gps_topic"] and options["odom_topic"]:
        raise SeqvprError("give --gps-topic or --odom-topic, not both")
    if options["restore"] and not options["state"]:
        raise SeqvprError("--restore starts from the state in --state: give --state PATH")
    if options["restore"] and not Path(options["state"]).is_file():
        raise SeqvprError(f"--restore: {options['state']}: no such state file")
    localizer = open_localizer(options, LocalizerSettings.k)  # the localiser's own top-K: the status shows the best
    if options["state"]:
        localizer.check_state_path(options["state"])  # at start, not when the node stops
    fix_topic = options["gps_topic"] or options["odom_topic"]
    settings = NodeSettings(options["camera"], camera_type(options["camera"], options["image_type"]), fix_topic,
                            (NAVSATFIX if options["gps_topic"] else ODOMETRY) if fix_topic else None, options["no_drop"],
                            options["frame_id"], Path(options["state"]) if options["state"] else None,
                            node_loop_settings(options), options["publish_images"])
    bus = Bus(options["domain"])
    running = LocalizerNode(localizer, bus, settings)
    if options["restore"]:
        running.restore(settings.state)
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    policy = "every frame in order" if settings.keep_all else "the newest frame when behind"
    loops = f", {LOOP_TOPIC}" if settings.loops else ""
    click.echo(f"seqvpr node: {options['map_dir']} ({localizer.saved.info.count} frames, {localizer.settings.method}); "
               f"listening on {settings.camera} ({settings.camera_type}, {policy}) in domain {bus.domain}; publishing "
               f"{POSE_TOPIC if running.track is not None else '(no pose: the map has no positions)'} and "
               f"{STATUS_TOPIC}{loops}; {RESET_TOPIC} restarts", err=True)
    running.run(stop)
    saved = f"; state saved to {settings.state}" if settings.state else ""
    found = f"; {running.loops_found} loop closures published" if settings.loops else ""
    click.echo(f"seqvpr node: stopped after {running.processed} frames ({running.inbox.received} received, "
               f"{running.inbox.dropped} dropped, {running.malformed} malformed){found}{saved}", err=True)


def node_loop_settings(options: dict[str, Any]):
    """The node's loop settings (None without --loops): causal windows of the localiser's length over the rows it
    describes."""
    from seqvpr.localization.loops import LoopSettings

    if not options["loops"]:
        if options["loop_exclude"] or options["loop_threshold"] is not None or options["loop_shortlist"]:
            raise SeqvprError("--loop-exclude, --loop-threshold and --loop-shortlist need --loops")
        return None
    try:
        return LoopSettings("matching", options["seq_len"], options["loop_exclude"],
                            threshold=options["loop_threshold"], shortlist=options["loop_shortlist"])
    except SettingError as error:  # the node spells the loop settings with --loop-
        raise SeqvprError(error.naming({**FLAGS, **LOOP_FLAGS})) from None


@click.command("play", epilog="""\b
Examples:
  seqvpr play drive.bag --topic /camera/image_raw/compressed --gps-topic /fix
  seqvpr play drive_ros2/ --rate 2 --frames 100:400""")
@click.argument("bag", type=click.Path())
@click.option("--topic", help="The image topic to publish  [default: the bag's only image topic].")
@click.option("--gps-topic", help="The NavSatFix topic to publish with it  [default: the bag's, else its Odometry].")
@click.option("--odom-topic", help="The nav_msgs/Odometry topic to publish with it.")
@click.option("--rate", type=POSITIVE, default=1.0, show_default=True, help="Times the recorded pace.")
@click.option("--frames", help="Publish camera frames START:STOP (in recorded order) and the fixes between them.")
@click.option("--wait", type=NONNEGATIVE_FLOAT, default=2.0, show_default=True,
              help="Seconds to wait for a subscriber to the camera topic before the first frame (0: none).")
@click.option("--domain", type=DOMAIN, help="DDS domain  [default: $ROS_DOMAIN_ID, else 0].")
@click.option("--record", type=OUT_FOLDER, help="Also record what the node publishes (status, pose, loops, "
              "matched images) into this ROS 2 bag folder; seqvpr view opens it as a localisation.")
def play(**options: Any) -> None:
    """Publish a bag's camera topic (and position topic) live over DDS at its recorded rate, as ros2 bag play."""
    from seqvpr.cli.progress import tqdm_progress
    from seqvpr.data.loaders.rosbag import BagTopics, is_rosbag
    from seqvpr.ros2.dds import Bus, require_cyclonedds
    from seqvpr.ros2.play import play_bag

    require_cyclonedds()
    if not is_rosbag(Path(options["bag"])):
        raise SeqvprError(f"{options['bag']}: not a ROS bag (a .bag file, or a ROS 2 bag folder with metadata.yaml)")
    if options["gps_topic"] and options["odom_topic"]:
        raise SeqvprError("give --gps-topic or --odom-topic, not both")
    topics = BagTopics(options["topic"], options["gps_topic"], options["odom_topic"])
    recording = None
    if options["record"]:
        from seqvpr.io import check_out_folder
        from seqvpr.ros2.record import BAG_MARKER, NodeRecording

        check_out_folder(options["record"], BAG_MARKER, [options["bag"]], "--record")
        recording = NodeRecording(options["domain"])
    played = play_bag(options["bag"], topics, Bus(options["domain"]), options["rate"], options["frames"],
                      options["wait"],
                      tqdm_progress)
    heard = "" if played.matched or options["wait"] == 0 else " (no subscriber matched before the first frame)"
    click.echo(f"played {played.frames} frames of {played.camera_topic}"
               + (f" and {played.fixes} fixes of {played.position_topic}" if played.position_topic else "")
               + f" in {played.seconds:.1f} s{heard}")
    if recording is not None:
        counts = recording.finish(options["record"])
        click.echo(f"recorded {', '.join(f'{n} on {t}' for t, n in counts.items() if n) or 'nothing'} into "
                   f"{options['record']}")
