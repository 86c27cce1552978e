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
import os
import threading
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import TYPE_CHECKING, Iterable, Iterator

from .stages import SceneTask, process_model, run_scenes, single_thread_numerics

if TYPE_CHECKING:
    from shadowcorr_client.records import UploadRecord

__all__ = ["run_local"]

_worker_model_key: tuple[str | None, str] | None = None  # (model_path, device) when the method needs the model


def _init_worker(model_path: str | None, device: str, needs_model: bool) -> None:
    global _worker_model_key
    _exit_with_driver()
    single_thread_numerics()
    if needs_model:
        _worker_model_key = (model_path, device)
        process_model(*_worker_model_key)  # now, not in the first scene's latency


def _exit_with_driver() -> None:
    """End this worker the moment the driver process ends, however it ends (SIGKILL included).

    Nothing else would.  An orphaned worker waits forever on the task queue, whose write
    end it holds itself (every worker holds both ends of the pool's queues); the
    forkserver that forked it runs until every holder of its "alive" pipe is gone, the
    workers included; and the resource tracker until the forkserver and workers are.  A
    parent-death signal (PR_SET_PDEATHSIG, Linux only) would take two: one in each
    worker, whose parent is the forkserver, not the driver, and one in the forkserver,
    set by an import side effect of a preloaded module.  One mechanism does it, on every
    platform: multiprocessing's parent sentinel, a pipe end that only the driver holds,
    kept open for each worker it starts.  It reads as end-of-file as soon as the
    driver's process is gone (a zombie included, unlike a poll of its pid).  Once the
    workers are gone, the forkserver and then the resource tracker see their pipes close
    and exit by themselves.
    """
    driver = mp.parent_process()
    assert driver is not None, "called in a pool worker"

    def exit_when_driver_ends() -> None:
        driver.join()
        os._exit(1)

    threading.Thread(target=exit_when_driver_ends, name="driver-watch", daemon=True).start()


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
    not yet started and kills the workers of those running; the workers also exit by
    themselves if this process dies.  As with any spawn or forkserver pool, a script
    calling this needs an ``if __name__ == "__main__":`` guard (the workers import the
    main module).
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
    finished = False
    try:
        while True:
            for task in pending_tasks:
                running.add(pool.submit(_run_scene, task))
                if len(running) >= 2 * workers:
                    break
            if not running:
                finished = True
                return
            done, running = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                yield future.result()
    finally:
        if not finished:
            # Stopped early (Ctrl-C, SIGTERM, an error): nobody will read the scenes still
            # running, and a resume redoes them (only this process writes the results
            # file), so end their workers now instead of waiting for them.  Python 3.14
            # has ProcessPoolExecutor.kill_workers for this; before, only the private map.
            for process in list(pool._processes.values()):
                process.kill()
        pool.shutdown(wait=True, cancel_futures=True)
