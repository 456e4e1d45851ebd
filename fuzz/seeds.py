"""Write the seed corpora of ``fuzz/corpus/`` that are made rather than found by fuzzing.

    python fuzz/seeds.py [config_set] [euroc_reader] [camera_truth_reader] [mcap_reader]

- ``config_set``: the presets of ``config/`` (``sim.toml`` lists every key) and a few
  ``--set`` lines;
- ``euroc_reader``: each file of the harness's valid dataset, as an input picking it;
- ``camera_truth_reader``: alike, and each again with the truth's other files left out;
- ``mcap_reader``: a short lockstep flight of the simulator, recorded by the project's own
  recorder with a 64x48 PNG camera, of which the first frames are written again by the
  project's ``RecordingWriter`` (the whole flight is 2 MB): the complete file, the same cut
  short in its last chunk (what ``log recover`` reads), a copy with uncompressed chunks, and
  a tiny uncompressed one (the first frame's messages without images nor config: 2 kB, so
  the fuzzer runs it fast and shrinks what it finds to a few hundred bytes).

The MAVLink corpus is the fuzzer's own, merged from a run (fuzz/README.md).
"""

from __future__ import annotations

import importlib
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fuzz import harness  # noqa: E402

#: The recorded flight: the dome's first route, its mission cut short.
FLIGHT_OVERRIDES = ["flight.mission_timeout_s=4", "recorder.camera_format=png",
                    "camera.width=64", "camera.height=48"]
#: The copies keep what was logged until the VINS finished this many frames, but the bulky
#: topics no reader needs; the tiny copy keeps one frame and no images, nor the config.
MCAP_FRAMES, TINY_FRAMES = 4, 1
MCAP_LEFT_OUT = ("/vins/map", "/depth/relative", "/depth/points", "/planner/primitives")
TINY_LEFT_OUT = MCAP_LEFT_OUT + ("/camera/image", "/truth/depth", "/mavlink/timesync")


def _write(target: str, seeds: dict[str, bytes]) -> None:
    folder = harness.FUZZ / "corpus" / target
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in seeds.items():
        (folder / name).write_bytes(data)


def config_seeds() -> dict[str, bytes]:
    """The presets as files (``sim.toml`` has every key), and overrides on a small file and on
    none."""
    root = harness.FUZZ.parent / "config"
    seeds = {f"preset-{path.stem}": path.read_bytes() for path in sorted(root.glob("*.toml"))}
    seeds["overrides"] = (b"[rescale]\nmethod = \"monotone_spline\"\n"
                          b"--set mavlink.url=serial:///dev/ttyTHS1:921600\n"
                          b"--set camera.mount_pitch_deg=-5\n--set log.level=DEBUG\n")
    seeds["only-overrides"] = (b"--set recorder.directory=/var/lib/companion/flights\n"
                               b"--set camera.distortion=[-0.28, 0.07, 0.0002, 1.8e-05]\n--set go.rc_channel=7\n")
    return seeds


def euroc_seeds(target: str = "euroc_reader") -> dict[str, bytes]:
    """Each file that the dataset harness ``target`` picks, its valid text, as the input
    picking it (named by its first byte and the file)."""
    module = importlib.import_module(f"fuzz.{target}")
    return {f"{index}-{Path(name).parent.name}-{Path(name).name}":
            bytes([index]) + module.VALID[name].encode() for index, name in enumerate(module.FILES)}


def camera_truth_seeds() -> dict[str, bytes]:
    """:func:`euroc_seeds` of the camera truth's harness, and each again with the truth's
    other files left out: without these the mutations would seldom flip the one bit that
    leaves them out."""
    from fuzz.camera_truth_reader import LEAVE_OUT

    seeds = euroc_seeds("camera_truth_reader")
    return seeds | {f"{data[0] | LEAVE_OUT}-{name.split('-', 1)[1]}":
                    bytes([data[0] | LEAVE_OUT]) + data[1:] for name, data in seeds.items()}


def mcap_seeds() -> dict[str, bytes]:
    """A flight's first frames as the project's writer writes them, whole and cut short."""
    with tempfile.TemporaryDirectory() as folder:
        flight = _fly(Path(folder))
        copy, plain, tiny = (Path(folder) / name for name in ("copy", "plain", "tiny"))
        _copy_start(flight, copy, MCAP_FRAMES, MCAP_LEFT_OUT)
        _uncompressed(copy, plain)
        _copy_start(flight, tiny, TINY_FRAMES, TINY_LEFT_OUT, keep_config=False)
        _uncompressed(tiny, plain.with_name("tiny-plain"))
        data = copy.read_bytes()
        return {"flight-start.mcap": data, "flight-start-cut.mcap": data[:len(data) * 3 // 4],
                "flight-start-uncompressed.mcap": plain.read_bytes(),
                "flight-tiny-uncompressed.mcap": plain.with_name("tiny-plain").read_bytes()}


def _uncompressed(source: Path, out: Path) -> None:
    """``source`` copied by ``log recover``'s own copy, its chunks left uncompressed, so that
    mutations reach the records rather than break the compression."""
    from mcap.writer import CompressionType, Writer

    from companion.recording import inspect

    with open(out, "xb") as file:
        inspect._copy(inspect._Readable(source),
                      Writer(file, chunk_size=64_000, compression=CompressionType.NONE))


def _fly(folder: Path) -> Path:
    from companion.config import load_config
    from companion.launch import simulated

    config = load_config(None, [f"recorder.directory={folder}", *FLIGHT_OVERRIDES])
    summary = simulated.run(config, simulated.SimMission(world="dome"), record=True)
    return Path(summary["recording"]["path"])


def _copy_start(source: Path, out: Path, frames: int, left_out: tuple[str, ...], *,
                keep_config: bool = True) -> None:
    """The messages of ``source`` logged until its ``frames``-th VINS frame (and all of its
    flight events), but those on ``left_out``, with its metadata (the config too when
    ``keep_config``), written by a RecordingWriter on the channels they need."""
    from mcap.reader import make_reader

    from companion.recording.options import RecorderOptions
    from companion.recording.topics import TOPICS
    from companion.recording.writer import COMPANION_METADATA, RecordingWriter

    with open(source, "rb") as file:
        reader = make_reader(file)
        metadata = next(record.metadata for record in reader.iter_metadata()
                        if record.name == COMPANION_METADATA)
        messages = [(channel.topic, message) for _, channel, message in
                    reader.iter_messages(log_time_order=True)
                    if channel.topic not in left_out]
    health = [message.log_time for topic, message in messages if topic == "/vins/health"]
    end = health[frames - 1]
    kept = {key: value for key, value in metadata.items() if keep_config or key != "config"}
    writer = RecordingWriter(out, RecorderOptions(), metadata=kept)
    messages = [(topic, message) for topic, message in messages
                if message.log_time <= end or topic == "/flight/events"]
    for topic in TOPICS:
        if any(name == topic.name for name, _ in messages):
            writer.add_channel(topic.name, topic.schema, droppable=topic.droppable)
    for topic, message in messages:
        writer.put(topic, message.log_time, lambda data=message.data: data, message.publish_time)
    writer.close()


SEEDS = {"config_set": config_seeds, "euroc_reader": euroc_seeds,
         "camera_truth_reader": camera_truth_seeds, "mcap_reader": mcap_seeds}

if __name__ == "__main__":
    for target in sys.argv[1:] or SEEDS:
        _write(target, SEEDS[target]())
