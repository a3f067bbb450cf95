"""Property-based fuzzing of every file reader: whatever a file holds, the reader returns what it
reads or refuses the file with its own named error (DatasetError, PlanError, RecordingError,
ConfigError: the commands turn each into a message and exit 2), within 512 MiB more memory;
never another exception. Inputs: files made from each format's own words with random values,
and valid files mutated (bytes flipped, cut, inserted, repeated)."""

from __future__ import annotations

import gzip
import io
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from swarmmap.shared.run.config import ConfigError, read_config_file
from swarmmap.shared.wire.codec import encode
from swarmmap.shared.wire.protocol import Samples, Tensor
from swarmmap.shared.world.cubicasa import parse_cubicasa
from swarmmap.shared.world.datasets import DatasetError, LaserLog, read_log, write_rosbag
from swarmmap.shared.world.floorplan import PlanError
from swarmmap.shared.world.plans import load_ros_map, read_image
from swarmmap.shared.world.recording import RecordingError, RecordingWriter, read_recording
from tests.fuzzing import mutation_of

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
SLOW = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
MEMORY_MIB = 512
WORK = Path(tempfile.mkdtemp(prefix="swarmmap-fuzz-"))
TRIED: dict[str, int] = {}


@pytest.fixture(autouse=True, scope="module")
def _report_inputs():
    yield
    print(f"\nfile readers fuzzed: {', '.join(f'{n} {s}' for s, n in sorted(TRIED.items()))} inputs")


def tried(reader: str) -> None:
    TRIED[reader] = TRIED.get(reader, 0) + 1


# ----------------------------------------------------------------- CARMEN logs

numbers = st.one_of(st.integers(-5, 2000).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                    st.sampled_from(["1e308", "-1e308", "nan", "inf", "0", "-0", "99999999999999999999", "0x10", ""]),
                    st.text(alphabet="0123456789.-e+", max_size=8))


@st.composite
def carmen_line(draw) -> str:
    word = draw(st.sampled_from(["FLASER", "ROBOTLASER1", "ODOM", "PARAM", "RAWLASER1", "# comment", "NOISE"]))
    if word == "FLASER" and draw(st.booleans()):  # a count that the fields may or may not match
        n = draw(st.integers(0, 40))
        fields = [str(n)] + [draw(numbers) for _ in range(n + draw(st.integers(-3, 10)))]
    else:
        fields = [draw(numbers) for _ in range(draw(st.integers(0, 30)))]
    return " ".join([word, *fields])


@FUZZ
@given(lines=st.lists(carmen_line(), max_size=30), zipped=st.booleans())
def test_carmen_logs_are_read_or_refused(memory_limit, lines, zipped):
    memory_limit(MEMORY_MIB)
    text = "\n".join(lines).encode()
    path = WORK / ("fuzz.log.gz" if zipped else "fuzz.log")
    path.write_bytes(gzip.compress(text) if zipped else text)
    tried("CARMEN")
    try:
        log = read_log(path)
    except DatasetError:
        return
    assert isinstance(log, LaserLog) and np.isfinite(log.poses).all()


# ----------------------------------------------------------------- bags (ROS 1, rosbag2 sqlite3 and MCAP)


def small_log() -> LaserLog:
    n, beams = 6, 24
    angles = np.linspace(-np.pi / 2, np.pi / 2, beams)
    poses = np.stack([np.linspace(0, 1, n), np.zeros(n), np.zeros(n)], axis=1)
    return LaserLog("fuzz", np.arange(n, dtype=np.float64) * 0.2, poses, angles, np.full((n, beams), 2.0), 4.0)


def bag_bytes(storage: str) -> dict[str, bytes]:
    """The files of a small bag of ``storage``, by name."""
    out = WORK / f"valid-{storage}"
    if not out.exists():
        if storage == "ros1":
            from rosbags.rosbag1 import Writer
            from rosbags.typesys import Stores, get_typestore

            store = get_typestore(Stores.ROS1_NOETIC)
            out.mkdir()
            log = small_log()
            with Writer(out / "fuzz.bag") as w:
                conn = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
                for k in range(len(log.t)):
                    header = store.types["std_msgs/msg/Header"](k, store.types["builtin_interfaces/msg/Time"](k, 0), "laser")
                    msg = store.types["sensor_msgs/msg/LaserScan"](header, -1.5, 1.5, 0.1, 0.0, 0.0, 0.1, 10.0,
                                                                   np.full(24, 2.0, np.float32), np.zeros(0, np.float32))
                    w.write(conn, k * 10**9, store.serialize_ros1(msg, "sensor_msgs/msg/LaserScan"))
        else:
            write_rosbag(small_log(), out, storage=storage)
    return {p.name: p.read_bytes() for p in out.iterdir()}


@SLOW
@given(data=st.data(), storage=st.sampled_from(["mcap", "sqlite3", "ros1"]))
def test_bags_are_read_or_refused(memory_limit, data, storage):
    files = bag_bytes(storage)
    target = data.draw(st.sampled_from(sorted(n for n in files if not n.endswith(".yaml"))))
    folder = WORK / f"fuzz-{storage}"
    folder.mkdir(exist_ok=True)
    for name, content in files.items():
        (folder / name).write_bytes(data.draw(mutation_of(content)) if name == target else content)
    memory_limit(MEMORY_MIB)
    tried(f"bag {storage}")
    try:
        read_log(folder / target if storage in ("ros1", "mcap") else folder)
    except DatasetError:
        pass


# ----------------------------------------------------------------- recordings (.swrec)


def recording_bytes() -> bytes:
    path = WORK / "valid.swrec"
    if not path.exists():
        w = RecordingWriter(path, robot=2, config={"run_id": "rec", "seed": 3}, plan={"floorplan": "procedural"})
        for i in range(3):
            w.add(encode(Samples(run="rec", sender=2, seq=i, t=0.1 * i, position=[0.0, 0.0],
                                 points=Tensor.of(np.zeros((4, 2), np.float32)), labels=Tensor.of(np.zeros(4, np.float32)))))
        w.close()
    return path.read_bytes()


@FUZZ
@given(data=st.data())
def test_recordings_are_read_or_refused(memory_limit, data):
    content = data.draw(mutation_of(recording_bytes()))
    memory_limit(MEMORY_MIB)
    path = WORK / "fuzz.swrec"
    path.write_bytes(content)
    tried("swrec")
    for partial in (False, True):
        try:
            read_recording(path, allow_incomplete=partial)
        except RecordingError:
            pass


# ----------------------------------------------------------------- images: floor plans and ROS maps


def png_bytes(mode: str = "L") -> bytes:
    img = Image.fromarray((np.indices((16, 16)).sum(0) % 2 * 255).astype(np.uint8)).convert(mode)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


@FUZZ
@given(data=st.data(), mode=st.sampled_from(["L", "RGBA", "1"]))
def test_images_are_read_or_refused(memory_limit, data, mode):
    content = data.draw(mutation_of(png_bytes(mode)))
    memory_limit(MEMORY_MIB)
    path = WORK / "fuzz.png"
    path.write_bytes(content)
    tried("PNG")
    try:
        read_image(path, "floor plan")
    except PlanError:
        pass


yaml_values = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(), st.text(max_size=12),
                        st.lists(st.floats(), max_size=4))


@SLOW
@given(doc=st.fixed_dictionaries({}, optional={"image": st.sampled_from(["map.pgm", "missing.pgm", "../x", ""]) | st.text(max_size=8),
                                               "resolution": yaml_values | st.floats(0.01, 0.2), "origin": yaml_values,
                                               "occupied_thresh": yaml_values, "free_thresh": yaml_values,
                                               "negate": yaml_values, "mode": st.sampled_from(["trinary", "scale", "raw", "x"])}),
       data=st.data())
def test_ros_maps_are_read_or_refused(memory_limit, doc, data):
    import yaml

    folder = WORK / "rosmap"
    folder.mkdir(exist_ok=True)
    img = Image.fromarray(np.pad(np.full((12, 12), 254, np.uint8), 2))
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    (folder / "map.pgm").write_bytes(data.draw(mutation_of(buf.getvalue())) if data.draw(st.booleans()) else buf.getvalue())
    (folder / "map.yaml").write_text(yaml.safe_dump(doc))
    memory_limit(MEMORY_MIB)
    tried("ROS map")
    try:
        load_ros_map(folder / "map.yaml", 0.05)
    except PlanError:
        pass


# ----------------------------------------------------------------- SVG plans and config files

SVG = ('<?xml version="1.0"?><svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 500 400"><g id="Model">'
       '<g id="Wall" class="Wall"><polygon points="90,90 310,90 310,100 90,100"/>'
       '<g id="Door" class="Door"><polygon points="150,90 200,90 200,100 150,100"/></g></g>'
       '<g id="Wall" class="Wall" transform="matrix(1,0,0,1,100,50)"><polygon points="200,50 210,50 210,250 200,250"/></g>'
       '</g></svg>')


@FUZZ
@given(data=st.data())
def test_svg_plans_are_read_or_refused(memory_limit, data):
    content = data.draw(mutation_of(SVG.encode()))
    memory_limit(MEMORY_MIB)
    tried("SVG")
    try:
        parse_cubicasa(content, "fuzz.svg")
    except PlanError:
        pass


CONFIG = b"preset: smoke\nrobots: 3\nlearner:\n  rounds: 20\n  model_shape: [2, 16, 1]\nworld:\n  rooms_x: 2\n"


@FUZZ
@given(data=st.data())
def test_config_files_are_read_or_refused(memory_limit, data):
    content = data.draw(st.one_of(mutation_of(CONFIG), st.binary(max_size=256)))
    memory_limit(MEMORY_MIB)
    path = WORK / "fuzz.yaml"
    path.write_bytes(content)
    tried("config YAML")
    try:
        read_config_file(path)
    except ConfigError:
        pass
