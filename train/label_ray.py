"""Labelling on a Ray cluster: `sgjax label ... --ray [ADDRESS]` (issue "Beyond one machine").

A driver (this process) plans the run exactly as `train.label.label` does (the same fixed grid of
blocks, the same resume rule) and hands blocks, one at a time, to a few Ray actors. Each actor loads the
object set and receives the Stage-1 database once (the driver's copy, through Ray's object store: every
worker matches on the very same primitives), then labels the blocks it is given with
`label.label_block` and writes each one itself, atomically, into the output directory. The directory must therefore be
reachable by every worker under the same path: one machine, or a shared filesystem (NFS, Lustre, ...).
An object store (S3, GCS) would need more than this module does: `label_block` writing to a local
temporary directory and uploading each finished .json/.npz pair with the object store's atomic put
(the .npz last, as here), and the resume check listing the bucket instead of the directory.

Guarantees (as for the serial run):
- resumable: blocks already on disk are skipped, by the driver when it plans and by the worker again
  just before it labels one;
- nothing lost or written twice when a worker dies: the block it held is queued again and given to a
  live or a freshly started actor; a shard is one atomic rename, and a block found on disk is skipped;
- the same samples as a serial run with the same seed: a scene's samples depend only on the config and
  the scene index, never on the process or the order (tests/test_label_distributed.py checks it).

Ray is an optional dependency (`pip install -e ".[distributed]"`); `train.label` never imports it.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import time

from sgjax.stage1.database import DBConfig, PrimitiveDB
from train import label as label_lib

INSTALL_HINT = 'Ray is not installed: pip install -e ".[distributed]" (or pip install "ray[default]")'


class WorkerFailures(RuntimeError):
    """More labelling workers died than `label_ray`'s max_failures allows (finished shards are kept)."""


def import_ray():
    """The `ray` module, or ImportError naming the extra that installs it."""
    try:
        import ray
    except ImportError as exc:
        raise ImportError(INSTALL_HINT) from exc
    return ray


@dataclasses.dataclass
class RayLabelRun:
    """What one `label_ray` call did (`summary` covers every shard in the directory, as `label`'s does).

    shards: the shard records written by this call ({"start", "end", "samples", "trials", "seconds",
    "worker"}), in the order they finished; skipped: blocks found on disk by a worker (already done);
    requeued: blocks given again after their worker died; restarts: actors started to replace dead ones.
    wall_seconds: from the first block handed out to the last one written (actor start-up excluded);
    setup_seconds: starting the actors and loading objects and database in them.
    """

    summary: label_lib.LabelSummary
    workers: int
    shards: list[dict]
    skipped: int
    requeued: int
    restarts: int
    wall_seconds: float
    setup_seconds: float

    @property
    def trials(self) -> int:
        return sum(r["trials"] for r in self.shards)

    @property
    def trials_per_second(self) -> float:
        """Trials of this call per second of wall time (all workers together)."""
        return self.trials / self.wall_seconds if self.wall_seconds > 0 else 0.0

    def lines(self) -> list[str]:
        scenes = sum(r["end"] - r["start"] for r in self.shards)
        return [
            (
                f"ray: {self.workers} workers wrote {len(self.shards)} shards ({scenes} scenes, {self.trials} trials) "
                f"in {self.wall_seconds:.0f} s: {self.trials_per_second:.1f} trials/s wall "
                f"(+{self.setup_seconds:.0f} s start-up); {self.skipped} blocks already done, "
                f"{self.requeued} re-queued after a worker died, {self.restarts} workers restarted"
            ),
            *self.summary.lines(),
        ]


class LabelWorker:
    """A Ray actor's state (wrapped by `ray.remote` in `label_ray`, so this module imports without ray):
    the object set, the Stage-1 labellers and the run's settings, loaded once by `setup`."""

    def __init__(
        self,
        out_dir: str,
        config: label_lib.LabelConfig,
        db: PrimitiveDB,
        backend: str,
        nthread: int,
        crash_marker: str | None = None,
    ):
        self.out_dir, self.config, self.db, self.backend, self.nthread = out_dir, config, db, backend, nthread
        self.crash_marker = crash_marker
        self.objects = self.labellers = self.identity = None

    def setup(self) -> dict:
        """Load the object set and build the labellers (an actor's one-off cost) -> the object set's
        identity (the driver checks it against its own: a node with other objects would make other data)."""
        from sgjax.stage1.pipeline import Stage1

        self.objects, self.identity = label_lib.prepare_objects(self.config, progress=False)
        stage1 = Stage1(self.db, self.config.stage1)
        self.labellers = label_lib.Labellers.make(self.config, stage1)
        return self.identity

    def label_block(self, start: int, end: int) -> list[dict]:
        """Label and write block [start, end) (`label.label_block`) -> its shard records ([] if on disk)."""
        return label_lib.label_block(
            self.out_dir, start, end, self.objects, self.labellers, self.config, self.identity,
            self.backend, self.nthread, on_scene=self._maybe_crash,
        )

    def _maybe_crash(self, index: int, samples: int) -> None:
        # Fault injection for tests and drills: the first worker to finish a scene while the marker file
        # is absent creates it and dies mid-block, before writing anything, the way a lost machine would.
        if self.crash_marker is None or os.path.exists(self.crash_marker):
            return
        try:
            fd = os.open(self.crash_marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)  # one crash per marker
        except FileExistsError:
            return
        os.write(fd, f"{os.getpid()} died after scene {index}\n".encode())
        os.close(fd)
        os._exit(1)


def label_ray(
    out_dir: str | os.PathLike,
    n_scenes: int,
    config: label_lib.LabelConfig = label_lib.LabelConfig(),
    *,
    db: DBConfig | PrimitiveDB = DBConfig(),
    address: str | None = None,
    workers: int | None = None,
    threads: int = 1,
    backend: str = "cpu",
    first_scene: int = 0,
    progress: bool = True,
    max_failures: int | None = None,
    crash_marker: str | os.PathLike | None = None,
) -> RayLabelRun:
    """Label scenes first_scene..n_scenes-1 into `out_dir` on Ray actors; the same files as `label.label`.

    address: None starts a local Ray cluster on this machine's cores (or uses the one `ray.init` already
    started in this process); else `ray.init(address=address)` ("auto", "ray://host:10001", "host:6379").
    workers: actors (default: the cluster's CPUs // threads), each reserving `threads` CPUs and running
    MuJoCo on that many threads. db: the Stage-1 database (a PrimitiveDB, or the DBConfig of one the
    driver loads, building it into its cache if needed), sent to every actor.
    max_failures: dead workers tolerated before giving up (default 2 * workers + 2; finished shards stay,
    a rerun resumes). crash_marker: a fault-injection hook (tests, drills): the first worker to finish a
    scene while this file is absent creates it and exits mid-block.
    Raises ImportError without ray, ValueError for bad arguments, data of another config in out_dir or a
    cluster it cannot reach, WorkerFailures after more than max_failures dead workers.
    """
    ray = import_ray()
    if not 0 <= first_scene < n_scenes:
        raise ValueError(f"need 0 <= first_scene < n_scenes, got first_scene {first_scene} and n_scenes {n_scenes}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if threads < 1:
        raise ValueError(f"threads per worker must be >= 1 with Ray, got {threads}")
    label_lib.check_backend(backend)
    out_dir = os.path.abspath(os.fspath(out_dir))  # actors may run elsewhere: no relative paths
    label_lib.check_out_dir(out_dir, config)
    # The driver validates the set and, on one machine, fills the cache the actors then read, instead of
    # every actor preparing the same meshes at once; the database likewise.
    from sgjax.stage1.database import load_database

    _, identity = label_lib.prepare_objects(config, progress=progress)
    database = load_database(db, progress=progress) if isinstance(db, DBConfig) else db
    todo = label_lib.pending_blocks(out_dir, n_scenes, config, first_scene)
    total = n_scenes - first_scene
    if not todo:  # everything is on disk: no cluster needed
        summary = label_lib.summarize(out_dir)
        return RayLabelRun(summary, workers=0, shards=[], skipped=0, requeued=0, restarts=0, wall_seconds=0.0, setup_seconds=0.0)
    started_ray = not ray.is_initialized()
    if started_ray:
        try:  # workers' own output (warnings, compile notices) stays in Ray's logs, not on this terminal
            ray.init(address=address or None, log_to_driver=False)
        except (ConnectionError, RuntimeError) as exc:
            where = f"the Ray cluster at {address!r}" if address else "a local Ray cluster"
            raise ValueError(f"could not start or reach {where}: {exc} (a remote one: `ray start --head` on it first)") from exc
    began = time.perf_counter()
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        n_workers = workers if workers is not None else max(1, cpus // threads)
        n_workers = min(n_workers, len(todo))  # an actor without a block would only cost its start-up
        max_failures = 2 * n_workers + 2 if max_failures is None else max_failures
        actor_class = ray.remote(num_cpus=threads, max_restarts=0)(LabelWorker)
        marker = None if crash_marker is None else os.path.abspath(os.fspath(crash_marker))
        args = (out_dir, config, ray.put(database), backend, threads, marker)  # one copy in the object store
        driver = _Driver(ray, actor_class, args, identity, max_failures)
        shards = driver.run(collections.deque(todo), n_workers, progress, total, total - sum(e - s for s, e in todo))
    finally:
        if started_ray:
            ray.shutdown()
    return RayLabelRun(
        summary=label_lib.summarize(out_dir),
        workers=n_workers,
        shards=shards,
        skipped=driver.skipped,
        requeued=driver.requeued,
        restarts=driver.restarts,
        wall_seconds=driver.finished - driver.first_block if driver.first_block else 0.0,
        setup_seconds=(driver.first_block or time.perf_counter()) - began,
    )


class _Driver:
    """The scheduling loop: one block in flight per actor, a dead actor's block queued again (first)."""

    def __init__(self, ray, actor_class, args: tuple, identity: dict, max_failures: int):
        self.ray, self.actor_class, self.args, self.identity = ray, actor_class, args, identity
        self.max_failures = max_failures
        self.failures = self.requeued = self.restarts = self.skipped = 0
        self.first_block: float | None = None
        self.finished = 0.0

    def run(self, queue: collections.deque, n_workers: int, progress: bool, total: int, initial: int) -> list[dict]:
        ray = self.ray
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total, initial=initial, unit="scene", desc=f"label (ray, {n_workers} workers)")
        actors: dict[int, object] = {}
        in_flight: dict = {}  # ObjectRef -> (slot, block or None for a setup call)
        shards: list[dict] = []

        def start(slot: int) -> None:
            actors[slot] = self.actor_class.remote(*self.args)
            in_flight[actors[slot].setup.remote()] = (slot, None)

        def give(slot: int) -> None:
            if queue:
                block = queue.popleft()
                if self.first_block is None:
                    self.first_block = time.perf_counter()
                in_flight[actors[slot].label_block.remote(*block)] = (slot, block)
            else:  # nothing left for it: free its CPUs for the others' last blocks
                ray.kill(actors.pop(slot))

        try:
            for slot in range(n_workers):
                start(slot)
            while in_flight:
                (ref,), _ = ray.wait(list(in_flight), num_returns=1)
                slot, block = in_flight.pop(ref)
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayActorError as exc:  # the process or its node died
                    self.failures += 1
                    if self.failures > self.max_failures:
                        raise WorkerFailures(
                            f"{self.failures} labelling workers died (last: {exc}); finished shards are kept, "
                            "rerun the same command to resume"
                        ) from exc
                    if block is not None:
                        queue.appendleft(block)  # first in line: a block is never lost
                        self.requeued += 1
                    ray.kill(actors.pop(slot), no_restart=True)
                    self.restarts += 1
                    start(slot)
                    continue
                except ray.exceptions.RayTaskError as exc:  # an error in our code: the same everywhere
                    raise exc.as_instanceof_cause() from None
                if block is None and result != self.identity:
                    raise ValueError(
                        f"a Ray worker's object set differs from the driver's ({result} != {self.identity}): "
                        "every node needs the same meshes (and sgjax version) to make the same data"
                    )
                if block is not None:
                    shards += result
                    self.skipped += not result
                    self.finished = time.perf_counter()
                    if bar is not None:
                        bar.update(block[1] - block[0])
                give(slot)
        finally:
            for actor in actors.values():
                ray.kill(actor, no_restart=True)
            if bar is not None:
                bar.close()
        return shards
