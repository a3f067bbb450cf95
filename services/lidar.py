"""A LiDAR streamer: one robot's scans in, labelled training points out; live or from a recording.

Run-book: ``swarmmap lidar --robot I --config RUN_DIR/config.yaml``.

- Live: subscribes to ``robots/<I>/scan``, applies the sensor model (Gaussian range noise,
  dropouts, max-range returns; :func:`swarmmap.shared.world.sensing.sensor_model`), samples free
  points along each beam and an occupied point at each hit, and publishes ``Samples`` on
  ``robots/<I>/samples``; the end of the traversal is passed on as ``last``.
  ``--record FILE`` also writes the served stream to a recording (see
  :mod:`swarmmap.shared.world.recording`), completed when the traversal ends or the streamer stops.
  At most ``INBOX_SCANS`` scans wait for the sensor model: when more come than it takes, the
  scans' subscription waits, and so does the world's reliable publisher (its back pressure:
  at ``world.time_scale`` 0 the world drives as fast as the streamers take its scans).
- Replay: ``--replay FILE`` needs no world: once its learner is alive it serves the
  recording's points, exactly as recorded, at the recorded rate times ``--replay-speed``
  (0: as fast as the learner takes them).
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import numpy as np

from swarmmap.shared.run.config import RunConfig, fail, task_robot
from swarmmap.shared.run.limits import SHARED_MEMORY_OFF, robot_budget, without_shared_memory
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.codec import decode, encode
from swarmmap.shared.wire.protocol import Keys, ProtocolError, Samples, Scan, Tensor
from swarmmap.shared.world.plans import plan_reference
from swarmmap.shared.world.recording import RecordingError, RecordingWriter, read_recording
from swarmmap.shared.world.sensing import beam_samples, sensor_model

log = logging.getLogger("lidar")
INBOX_SCANS = 16  # scans that may wait for the sensor model (a few seconds of scans at any scan rate)


class HeldUntilMatched:
    """The samples publisher, holding back what it is given until this session knows the
    learner's subscription: a learner's liveliness token (which lets the world drive) can arrive
    before its subscription, and Zenoh drops what no known subscriber matches, so the first scans'
    points would be lost. At most ``max_bytes`` or ``seconds`` are held (then they go anyway, with
    a warning); the last one waits up to ``seconds`` for the match. Never blocks the scans' inbox
    before then (its back pressure holds the world's publisher)."""

    def __init__(self, out, robot: int, max_bytes: int = 8 << 20, seconds: float = 10.0):
        self.out, self.robot, self.max_bytes, self.seconds = out, robot, max_bytes, seconds
        self.held: list[bytes] | None = []
        self.held_bytes = 0
        self.since: float | None = None

    def put(self, payload: bytes, last: bool, stop: threading.Event) -> None:
        if self.held is None:
            self.out.put_bytes(payload)
            return
        self.since = self.since or time.monotonic()
        self.held.append(payload)
        self.held_bytes += len(payload)
        waited = time.monotonic() - self.since
        matched = not Bus.wait_matched([self.out], max(0.0, self.seconds - waited) if last else 0.0, stop)
        if matched or last or self.held_bytes >= self.max_bytes or waited >= self.seconds:
            if not matched:
                log.warning("robot %d: no subscriber of its samples known after %.0f s; sending %d held back anyway",
                            self.robot, time.monotonic() - self.since, len(self.held))
            for held in self.held:
                self.out.put_bytes(held)
            self.held = None


class Inbox:
    """Scans waiting for the sensor model, at most ``size``. A full inbox holds the Zenoh callback
    that puts a scan until there is room (or the streamer stops: the scan is then dropped), so
    that a slow streamer slows the world's publisher instead of growing without bound."""

    def __init__(self, stop: threading.Event, size: int = INBOX_SCANS):
        self.stop = stop
        self.queue: queue.Queue[Scan] = queue.Queue(size)

    def put(self, scan: Scan) -> None:
        """Add ``scan``, waiting while the inbox is full (the Zenoh callback: back pressure)."""
        while not self.stop.is_set():
            try:
                self.queue.put(scan, timeout=0.2)
                return
            except queue.Full:
                continue

    def get(self, timeout: float) -> Scan | None:
        """The oldest scan, or None when none came within ``timeout`` seconds."""
        try:
            return self.queue.get(timeout=timeout)
        except queue.Empty:
            return None


class SensorModel:
    """Turns ideal scans into labelled points the way this robot's sensor sees them."""

    def __init__(self, cfg: RunConfig, robot: int):
        self.cfg = cfg
        self.rng = np.random.default_rng([cfg.seed, robot, 1])

    def samples(self, scan: Scan, again: bool = False) -> Samples:
        """``scan``'s labelled points; a scan served ``again`` (a restarted world's) draws from a
        generator of its own, so the next new scan's points are those of a run without the restart."""
        s = self.cfg.lidar
        rng = np.random.default_rng([self.cfg.seed, int(scan.sender), 2, int(scan.seq)]) if again else self.rng
        ranges, hit, valid = sensor_model(scan.ranges.numpy(), scan.hit.numpy().astype(bool), rng,
                                          noise_std=s.range_noise_std_m, dropout_prob=s.dropout_prob,
                                          min_range=self.cfg.lidar_min_range_m(), max_range=scan.max_range)
        points, labels = beam_samples(scan.pose[:2], scan.angles.numpy()[valid], ranges[valid], hit[valid], scan.max_range,
                                      s.samples_per_beam, s.occupied_depth_m, sampling=s.sampling, rng=rng,
                                      free_on_max_range=s.free_on_max_range)
        return Samples(run=scan.run, sender=scan.sender, seq=scan.seq, t=scan.t, position=list(scan.pose[:2]),
                       points=Tensor.of(points, "<f4"), labels=Tensor.of(labels, "<f4"), last=scan.last, leg=scan.leg,
                       leg_end=scan.leg_end)


def robot_file(template: str, robot: int) -> str:
    """A per-robot file name: ``{robot}`` in ``template`` becomes the id."""
    return template.replace("{robot}", str(robot))


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """The streamer's main loop; returns the process exit status."""
    robot = task_robot(cfg.lidar.robot, cfg.robots, "lidar.robot")
    cfg, off = without_shared_memory(cfg, robot_budget(cfg, robot))
    if off:
        log.info("robot %d's budget: %s", robot, SHARED_MEMORY_OFF)
    if cfg.lidar.record and cfg.lidar.replay:
        fail("config error:\n  lidar.record, lidar.replay: choose one")
    if cfg.lidar.replay:
        return replay(cfg, robot, robot_file(cfg.lidar.replay, robot), stop)
    return live(cfg, robot, stop)


def live(cfg: RunConfig, robot: int, stop: threading.Event) -> int:
    keys = Keys(cfg.key_prefix, cfg.run_id)
    inbox = Inbox(stop)
    model = SensorModel(cfg, robot)
    recorder = None
    if cfg.lidar.record:
        recorder = RecordingWriter(robot_file(cfg.lidar.record, robot), robot, cfg.model_dump(mode="json"),
                                   plan_reference(cfg.plan()))
    with Bus.open(cfg.zenoh, keys, "lidar", robot) as bus:
        bus.end_with_run(stop)
        out = HeldUntilMatched(bus.publisher(keys.samples(robot)), robot)
        bus.subscribe(keys.scan(robot), Scan, inbox.put, direct=True)  # a full inbox holds the world back
        bus.announce()
        count = points = repeated = 0
        newest = -1
        try:
            while not stop.is_set():
                if (scan := inbox.get(timeout=0.2)) is None:
                    continue
                again = scan.seq <= newest  # a restarted world drives its traversal again from its start
                if again and repeated == 0:
                    log.warning("robot %d: scan %d again after scan %d (the world restarted its traversal?): the learner "
                                "drops what it has; its sampling here goes on as if they had not come", robot, scan.seq, newest)
                repeated += again
                newest = max(newest, scan.seq)
                samples = model.samples(scan, again)
                payload = encode(samples)
                out.put(payload, scan.last, stop)
                if recorder is not None:
                    recorder.add(payload)
                count += 1
                points += samples.labels.shape[0]
                if scan.last:
                    log.info("robot %d traversal done: %d scans -> %d labelled points", robot, count, points)
                    if recorder is not None:
                        log.info("recorded %d frames to %s", count, recorder.close())
                        recorder = None
        finally:
            if recorder is not None:  # stopped before the end: what was served is whole
                log.info("recorded %d frames to %s (stopped before the traversal ended)", count, recorder.close())
    return 0


def replay(cfg: RunConfig, robot: int, path: str, stop: threading.Event) -> int:
    try:
        rec = read_recording(path, allow_incomplete=cfg.lidar.replay_incomplete)
    except RecordingError as exc:
        log.error("recording refused: %s", exc)
        return 2
    if rec.robot != robot:
        log.error("recording refused: %s: it holds robot %d, this streamer serves robot %d", path, rec.robot, robot)
        return 2
    recorded_run = rec.config.get("run_id", "")
    messages = []
    for i, (t, payload) in enumerate(rec.frames):
        try:
            msg = decode(payload, Samples, run=recorded_run, sender=robot)
        except ProtocolError as exc:
            log.error("recording refused: %s: frame %d: %s", path, i + 1, exc)
            return 2
        last = msg.last or i == len(rec.frames) - 1  # an incomplete recording still ends its traversal
        messages.append((t, msg.model_copy(update={"run": cfg.run_id, "last": last})))
    keys = Keys(cfg.key_prefix, cfg.run_id)
    with Bus.open(cfg.zenoh, keys, "lidar", robot) as bus:
        bus.end_with_run(stop)
        out = bus.publisher(keys.samples(robot))
        bus.announce()
        if bus.wait_alive("learner", {str(robot)}, cfg.consumers_wait_s(), stop):
            log.warning("replaying although learner %d is not alive", robot)
        elif Bus.wait_matched([out], 10.0, stop):
            log.warning("replaying although learner %d's subscription is not known yet (its first frames may be lost)", robot)
        speed = cfg.lidar.replay_speed
        start = time.monotonic()
        for t, msg in messages:
            if stop.is_set():
                break
            if speed > 0 and (ahead := start + t / speed - time.monotonic()) > 0:
                stop.wait(ahead)
            out.put(msg)
        log.info("robot %d: replayed %d frames from %s%s", robot, len(messages), path,
                 "" if rec.complete else " (incomplete recording)")
        stop.wait()
    return 0
