"""Batch correspondence over whole datasets: ``shadowcorr batch``.

An application built on the library, like the HTTP service: it finds every scene of a
dataset (the discovery of ``shadowcorr-client upload-dataset``), runs the library's
``prepare`` -> ``embed`` -> ``assign`` on each, and appends one JSON line per scene to a
results file in the ``upload-dataset`` record shape, resumable.  Two engines:

* ``local`` -- a process pool on this machine (:mod:`shadowcorr_batch.local`);
* ``ray`` -- a Ray Data pipeline on a local Ray instance or a cluster
  (:mod:`shadowcorr_batch.ray_engine`; optional extra ``pip install "shadowcorr[ray]"``).

::

    from shadowcorr_batch import BatchOptions, run_batch

    run = run_batch("datasets/field7", "out/field7.jsonl", BatchOptions(engine="ray", workers=2))
    print(run.summary)
"""

from typing import TYPE_CHECKING

from shadowcorr._lazy import lazy_exports

# Lazy (PEP 562): `shadowcorr --help` registers the batch command without importing torch.
_EXPORTS = {"BatchOptions": "runner", "BatchRun": "runner", "plan_batch": "runner", "run_batch": "runner",
            "SceneTask": "stages"}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from .runner import BatchOptions, BatchRun, plan_batch, run_batch
    from .stages import SceneTask
