"""`ftcal db start|stop` as docs/scaling.md runs it, from a directory the ``postgres`` user cannot enter (a
checkout under /root): the server starts, serves both databases, runs as ``postgres`` (never as root) and
stops. Run as another user, the server is that user's and the cluster stays where it was asked."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.tools import db
from tests.pgserver import free_port


def test_db_start_and_stop_where_postgres_cannot_enter(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import psycopg

    if db.find_bindir() is None:
        reason = "PostgreSQL server binaries absent (apt-get install postgresql)"
        if os.environ.get("CI") == "true":
            pytest.fail(f"{reason}: .ci/run installs them in CI")
        pytest.skip(reason)
    home = tmp_path / "home"
    home.mkdir(mode=0o700)
    data = home / "repo" / ".pgdata"
    if os.geteuid() == 0:  # the precondition of the case: postgres cannot enter the home
        enter = subprocess.run(["runuser", "-u", "postgres", "--", "test", "-x", str(home)], check=False)
        assert enter.returncode != 0
    port = free_port()
    try:
        assert main(["db", "start", str(data), "--port", str(port)]) == 0, capsys.readouterr().err
        out = capsys.readouterr().out
        assert f"postgresql://ftcal@127.0.0.1:{port}/ftcal" in out
        for database in (db.DATABASE, db.MLFLOW_DATABASE):
            with psycopg.connect(db.url(port, database=database)) as conn:
                assert conn.execute("SELECT current_database()").fetchone() == (database,)
        owner = (data.resolve() / "postmaster.pid").owner()  # the server's user
        assert owner != "root"
        if os.geteuid() == 0:
            assert owner == "postgres" and data.is_symlink() and "kept in" in out
        assert main(["db", "stop", str(data)]) == 0
        assert not (data.resolve() / "postmaster.pid").exists()
    finally:
        if (data.resolve() / "postmaster.pid").exists():
            db.stop(data)
        if data.is_symlink():
            shutil.rmtree(data.resolve(), ignore_errors=True)
