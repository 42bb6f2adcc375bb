"""Session fixtures: a real PostgreSQL server on loopback (and an MLflow tracking server on it).

The server is the machine's own (`pipeline.tools.db`, Debian's ``postgresql`` package), in a throwaway
cluster with fsync off. Without the binaries the tests that need it are skipped with the reason, except
in CI (CI=true), where .ci/run installs them and their absence is a failure.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from pipeline.tools import db


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def create_database(url: str, name: str) -> str:
    """Create database `name` on the server of `url` unless it exists; return its URL."""
    import psycopg

    with psycopg.connect(url, autocommit=True) as conn:
        if conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (name,)).fetchone() is None:
            conn.execute(f'CREATE DATABASE "{name}"')
    return url.rsplit("/", 1)[0] + f"/{name}"


@pytest.fixture(scope="session")
def pg_url() -> Iterator[str]:
    """URL of database ``ftcal`` on a PostgreSQL server started for this test session."""
    if db.find_bindir() is None:
        reason = "PostgreSQL server binaries absent (apt-get install postgresql)"
        if os.environ.get("CI") == "true":
            pytest.fail(f"{reason}: .ci/run installs them in CI")
        pytest.skip(reason)
    base = Path(tempfile.mkdtemp(prefix="ftcal-pg-"))
    base.chmod(0o755)  # the server runs as user postgres when the tests run as root
    settings = {"fsync": "off", "synchronous_commit": "off", "full_page_writes": "off"}
    try:
        yield db.start(base / "data", free_port(), settings)
    finally:
        if (base / "data" / "postmaster.pid").exists():
            db.stop(base / "data")
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture(scope="session")
def mlflow_server(pg_url: str) -> Iterator[str]:
    """URL of an `mlflow server` whose backend store is a database of the session's PostgreSQL and whose
    artifacts it serves from a temporary directory."""
    backend = create_database(pg_url, "mlflow").replace("postgresql://", "postgresql+psycopg://")
    artifacts = Path(tempfile.mkdtemp(prefix="ftcal-mlartifacts-"))
    port = free_port()
    log = open(artifacts.parent / f"{artifacts.name}.log", "w")  # noqa: SIM115 (open while it runs)
    cmd = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", backend]
    cmd += ["--artifacts-destination", artifacts.as_uri(), "--host", "127.0.0.1", "--port", str(port)]
    cmd += ["--workers", "1"]
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"mlflow server did not start: see {log.name}")
            time.sleep(0.5)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
        shutil.rmtree(artifacts, ignore_errors=True)
