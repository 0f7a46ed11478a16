"""Certify a manifest on a Dask cluster (optional extra ``larc_jax[distributed]``).

:func:`certify_manifest_dask` reads the manifest on the client, sends each pending chunk's rows
to a worker as one task (:func:`larc_jax.drivers.manifest.certify_chunk`, the same function the
single-process path runs) and collects the chunk summaries as they finish. Workers write their
part files straight into the results (and leaves) folders, which must therefore be on storage
every worker can reach (a shared file system; on one machine, any folder). Resuming, refusal of
a folder written for another run, and per-row errors are exactly as in
:mod:`larc_jax.drivers.manifest`.

Workers load the robot once per process (``ManifestJob.robot_file``, or PIPER through
``LARC_PIPER_DESCRIPTION`` — set it in the workers' environment) and compile the kernels once
per process. At most ``max_in_flight`` chunks are submitted at a time, so the client's memory
stays bounded for manifests of any length.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from ..errors import LarcInputError
from .manifest import ManifestJob, certify_chunk, certify_manifest

__all__ = ["certify_manifest_dask"]


def _client(scheduler):
    try:
        from dask.distributed import Client
    except ImportError:
        raise LarcInputError(
            "--dask needs dask.distributed: pip install 'larc_jax[distributed]' (or dask[distributed])") from None
    if isinstance(scheduler, Client):
        return scheduler, False
    try:
        return Client(scheduler, timeout=30), True
    except (OSError, TimeoutError, ValueError) as exc:
        raise LarcInputError(f"--dask {scheduler}: cannot connect to the Dask scheduler ({exc})") from None


def certify_manifest_dask(manifest: str | Path, job: ManifestJob, scheduler,
                          on_chunk: Callable[[dict], None] | None = None, max_in_flight: int | None = None) -> dict:
    """Certify every pending chunk of ``manifest`` on a Dask cluster.

    ``scheduler`` is a scheduler address (``tcp://host:8786``) or a ``dask.distributed.Client``.
    Returns the same summary as :func:`larc_jax.drivers.manifest.certify_manifest`, whose loop this runs
    (the cluster is reached only after the results folder's state was checked).
    """

    def on_dask(job: ManifestJob, todo):
        from dask.distributed import as_completed

        client, owned = _client(scheduler)
        try:
            workers = max(1, len(client.scheduler_info().get("workers", {})))
            limit = max_in_flight or 4 * workers
            running = as_completed()
            for k, rows in todo:
                running.add(client.submit(certify_chunk, job, k, rows, pure=False))
                while running.count() >= limit:
                    yield next(running).result()  # a worker's exception is re-raised here
            for future in running:
                yield future.result()
        finally:
            if owned:
                client.close()

    return certify_manifest(manifest, job, on_chunk, runner=on_dask)
