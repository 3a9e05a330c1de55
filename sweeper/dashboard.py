"""``sweeper dashboard SPEC``: serve optuna-dashboard on the study's storage.

The server reads the same database the driver writes (SQLite in WAL mode, so a live study
can be watched), and shows what the driver (while a launch runs, ``sweeper.results._live``)
and ``sweeper aggregate`` saved into the study: the comparison table and the per-method
curves and AUC figures, and the comparison in the study note; each trial's page
plays its episode videos (the study's artifact store, ``sweeper.storage._artifacts``). It binds to
127.0.0.1 by default: the dashboard can edit notes and delete studies, so expose it
beyond this machine only on purpose (``--host 0.0.0.0``). Ctrl-C or SIGTERM stops it.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sweeper.spec import StudySpec

#: optuna-dashboard lists a study's plotly figures in the order a Python set of their ids
#: iterates, which follows the process's string-hash seed, so it changed at every start.
#: The sweep now saves one figure (``sweeper.results._dashboard_card.COMPARISON_ID``), whose
#: place needs no seed; a study whose figures were saved before, six of them, until it is
#: aggregated again, shows them under this seed with the comparison table first
#: (``sweeper dashboard`` runs under it)
HASH_SEED = "0"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``sweeper dashboard`` (``sweeper.cli`` adds the spec and --storage)."""
    parser.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1)"
    )
    parser.add_argument(
        "--port",
        type=_port,
        default=8080,
        help="port to listen on; 0 picks a free one (default: 8080)",
    )


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be an integer in [0, 65535], got {text!r}"
        ) from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"must be an integer in [0, 65535], got {port}")
    return port


def run(spec: StudySpec, args: argparse.Namespace) -> int:
    """``sweeper dashboard``: serve until stopped; exit 0, or 2 when there is no study to
    show (no database file, an empty database, no such study), the storage cannot be read,
    or the address cannot be listened on."""
    from sweeper.storage import artifact_location, open_study

    try:
        artifacts = artifact_location(spec)
        if os.environ.get("PYTHONHASHSEED") != HASH_SEED and sys.argv[1:2] == ["dashboard"]:
            with open_study(spec.storage_url, spec.study, write=False):
                pass  # no such study: the error, here, rather than after the restart
            # the same command again, under HASH_SEED (only where this process is it)
            environment = {**os.environ, "PYTHONHASHSEED": HASH_SEED}
            os.execve(sys.executable, sys.orig_argv, environment)
        return serve(spec.storage_url, spec.study, args.host, args.port, artifacts=artifacts)
    except ValueError as e:  # StorageError, NoStudy
        print(f"sweeper dashboard: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the port is taken, the host is not ours
        print(f"sweeper dashboard: cannot listen on {args.host}:{args.port}: {e}", file=sys.stderr)
        return 2


def serve(
    storage_url: str,
    study_name: str,
    host: str = "127.0.0.1",
    port: int = 8080,
    ready: Callable[[str], None] | None = None,
    artifacts: str | None = None,
) -> int:
    """Serve optuna-dashboard for ``storage_url`` until Ctrl-C or SIGTERM; return 0.

    ``ready(url)`` is called with the study's page once the server listens (default: print
    it on stdout). ``artifacts`` is the study's artifact location (``sweeper.storage._artifacts``):
    the trial pages then play the episode videos. Raises ValueError when the storage does
    not hold ``study_name``.
    """
    from socketserver import ThreadingMixIn
    from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

    import optuna_dashboard

    from sweeper.storage import ArtifactStore, open_study

    class Server(ThreadingMixIn, WSGIServer):
        daemon_threads = True  # a slow browser request never blocks shutdown

    class QuietHandler(WSGIRequestHandler):
        def log_message(self, format: str, *args: Any) -> None:  # one line per request: noise
            pass

    store_of_artifacts = ArtifactStore(artifacts) if artifacts is not None else None
    # not read-only: the dashboard edits notes; create=False: an absent study is an error
    with open_study(storage_url, study_name, write=True, create=False) as store:
        app = optuna_dashboard.wsgi(store.storage, artifact_store=store_of_artifacts)
        server = make_server(host, port, app, server_class=Server, handler_class=QuietHandler)
        url = f"http://{host}:{server.server_port}/dashboard/studies/{store.study_id}"
        main_thread = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, _raise_interrupt) if main_thread else None
        try:
            if ready is None:
                print(f"optuna-dashboard: {url}  (Ctrl-C stops it)", flush=True)
            else:
                ready(url)
            server.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            if main_thread:
                signal.signal(signal.SIGTERM, previous)
            server.server_close()
    return 0


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt
