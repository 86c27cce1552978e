"""``--engine local``: a process pool on this machine, one whole scene per worker at a time.

Each worker loads the model once and runs prepare -> embed -> assign on its scene.
Measured against the alternative (workers prepare and assign, the parent batches the
network; ``benchmarks/bench_batch.py --parent-network``): no faster on 2 cores (79 vs 83 s
for 50 scenes, within the machine's noise) and more CPU per scene (shipping every voxel
scene to the parent and back, a parent competing with the workers for the cores), since
the forward pass was about a tenth of a scene's CPU time (a quarter with the ``fused`` method);
so the simpler design stays.
"""

from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import TYPE_CHECKING, Iterable, Iterator

from .stages import SceneTask, process_model, run_scenes, single_thread_numerics

if TYPE_CHECKING:
    from clients.records import UploadRecord

__all__ = ["run_local"]

_worker_model_key: tuple[str | None, str] | None = None  # (model_path, device) when the method needs the model


def _init_worker(model_path: str | None, device: str, needs_model: bool) -> None:
    global _worker_model_key
    single_thread_numerics()
    if needs_model:
        _worker_model_key = (model_path, device)
        process_model(*_worker_model_key)  # now, not in the first scene's latency


def _run_scene(task: SceneTask) -> "UploadRecord":
    (record,) = run_scenes([task], process_model(*_worker_model_key) if _worker_model_key else None)
    return record


def run_local(
    tasks: Iterable[SceneTask],
    *,
    workers: int,
    model_path: str | None = None,
    device: str = "cpu",
    needs_model: bool = True,
) -> Iterator["UploadRecord"]:
    """Run every task in ``workers`` processes; yield each record as soon as its scene is done.

    At most ``2 * workers`` scenes are submitted at once, so a dataset of any size never
    sits in memory.  Closing the generator (Ctrl-C in the consumer) cancels the scenes
    not yet started.  As with any spawn or forkserver pool, a script calling this needs
    an ``if __name__ == "__main__":`` guard (the workers import the main module).
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    pending_tasks = iter(tasks)
    # forkserver, not fork: the parent may have run torch, whose thread pools do not survive
    # a fork.  The server process imports the pipeline once and every worker forks from it,
    # instead of each spawned worker importing torch again (seconds per worker).
    context = mp.get_context("forkserver")
    context.set_forkserver_preload([__name__])
    pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker,
                               initargs=(model_path, device, needs_model))
    running: set[Future] = set()
    try:
        while True:
            for task in pending_tasks:
                running.add(pool.submit(_run_scene, task))
                if len(running) >= 2 * workers:
                    break
            if not running:
                return
            done, running = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                yield future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
