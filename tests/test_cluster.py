"""The embedded Dask cluster (stages.cluster) closes without a traceback, and what its
workers log while they work still shows."""

from __future__ import annotations

import logging

from distributed import WorkerPlugin
from distributed.comm.core import CommClosedError


def _log_while_working(message: str) -> bool:
    logging.getLogger("distributed.worker").error(message)
    return True


class _HeartbeatFailsAtClose(WorkerPlugin):
    """What a loaded machine does at shutdown, made certain: once its worker is closing,
    the heartbeat meets the closed scheduler and Dask logs it with its traceback (as
    distributed.worker.Worker.heartbeat does)."""

    def teardown(self, worker) -> None:
        try:
            raise CommClosedError("in <TCP (closed) ConnectionPool.heartbeat_worker>: closed")
        except OSError:
            logging.getLogger("distributed.worker").exception(
                "Failed to communicate with scheduler during heartbeat."
            )


def test_an_embedded_cluster_closes_quietly_and_shows_errors_while_working(capfd):
    from stages.cluster import dask_client

    with dask_client(1) as client:
        client.register_plugin(_HeartbeatFailsAtClose(), name="heartbeat-fails-at-close")
        assert client.submit(_log_while_working, "an error logged by a task", pure=False).result()
    err = capfd.readouterr().err
    assert "an error logged by a task" in err, err
    assert "Traceback" not in err and "Failed to communicate" not in err, err
