"""`ftcal db start|stop`: a local PostgreSQL server for shared Optuna studies and an MLflow server.

``ftcal db start [DIR] [--port 5432]`` creates a database cluster in DIR (default ``.pgdata`` at the repo
root) on first use, starts the server on 127.0.0.1:PORT with databases
``ftcal`` for Optuna and ``mlflow`` for an MLflow server, owned by the role ``ftcal`` (trust
authentication on loopback only: a local, single-user server), and prints their URLs;
``ftcal db stop [DIR]`` stops it. It runs the PostgreSQL binaries of the machine (Debian: ``apt-get install
postgresql``); run as root, the server runs as the ``postgres`` user, as PostgreSQL requires, and where that
user cannot enter the way to DIR (a checkout under /root, or any home it may not read), the cluster is kept
in that user's home (``~postgres/ftcal/<name>-<hash>``) with DIR a link to it. A lab with its own server
skips this and sets ``train.storage`` (or ``$FTCAL_OPTUNA_STORAGE``) to its URL.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import pwd
import shutil
import subprocess
from pathlib import Path
from typing import Any

from pipeline.core.errors import FtcalError

DEFAULT_DIR = ".pgdata"
DEFAULT_PORT = 5432
ROLE = DATABASE = "ftcal"  # the role, and the database of the Optuna studies
MLFLOW_DATABASE = "mlflow"  # the MLflow server's backend store (its own tables and schema migrations)
_RUN_AS = "postgres"  # PostgreSQL refuses to run as root


class DatabaseError(FtcalError):
    """The PostgreSQL server cannot be found, created, started or stopped."""


def find_bindir() -> Path | None:
    """The directory of the PostgreSQL server binaries (initdb, pg_ctl), or None if not installed."""
    found = shutil.which("pg_ctl")
    if found and Path(found).resolve().with_name("initdb").exists():
        return Path(found).resolve().parent
    versions = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"), key=lambda p: int(p.parts[-3]))
    return versions[-1].parent if versions else None


def _as_server_user(cmd: list[str]) -> list[str]:
    return ["runuser", "-u", _RUN_AS, "--", *cmd] if os.geteuid() == 0 else cmd


def _run(cmd: list[str], what: str) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(_as_server_user(cmd), capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        detail = (proc.stderr or proc.stdout).strip().splitlines()
        raise DatabaseError(f"{what}: {detail[-1] if detail else f'exit status {proc.returncode}'}")
    return proc


def _server_can_enter(path: Path) -> bool:
    """Whether the server's user can reach `path` (search permission on every directory on the way)."""
    while not path.exists():
        path = path.parent
    check = subprocess.run(_as_server_user(["test", "-x", str(path)]), capture_output=True, check=False)
    return check.returncode == 0


def cluster_dir(data_dir: Path) -> Path:
    """The directory that holds cluster `data_dir`: itself, or, run as root where the server's user cannot
    reach it, a directory in that user's home, `data_dir` becoming a link to it (module docstring)."""
    data_dir = data_dir.absolute()
    if os.geteuid() != 0 or data_dir.is_symlink() or _server_can_enter(data_dir.parent):
        return data_dir.resolve()
    if data_dir.is_dir() and not any(data_dir.iterdir()):
        data_dir.rmdir()  # an empty one, left by a start that failed here
    if data_dir.exists():
        raise DatabaseError(
            f"{data_dir}: the {_RUN_AS} user cannot enter it and PostgreSQL does not run as root: move it "
            f"away and run `ftcal db start` again (the cluster then lives in ~{_RUN_AS}/ftcal)"
        )
    digest = hashlib.sha256(str(data_dir).encode()).hexdigest()[:12]
    home = Path(pwd.getpwnam(_RUN_AS).pw_dir) / "ftcal"
    target = home / f"{data_dir.parent.name or 'root'}{data_dir.name}-{digest}"
    target.mkdir(parents=True, exist_ok=True)
    shutil.chown(home, _RUN_AS, _RUN_AS)
    data_dir.parent.mkdir(parents=True, exist_ok=True)
    data_dir.symlink_to(target, target_is_directory=True)
    return target


def url(port: int, host: str = "127.0.0.1", database: str = DATABASE) -> str:
    """The URL of one of the local server's databases."""
    return f"postgresql://{ROLE}@{host}:{port}/{database}"


def start(data_dir: Path, port: int = DEFAULT_PORT, settings: dict[str, str] | None = None) -> str:
    """Create (first time) and start the server of cluster `data_dir` on 127.0.0.1:`port`; return its URL.

    `settings` are extra server settings (``-c key=value``), e.g. ``{"fsync": "off"}`` for throwaway tests.
    Its log is ``<data_dir>/server.log``; its Unix socket is in `data_dir`.
    """
    bindir = find_bindir()
    if bindir is None:
        raise DatabaseError("PostgreSQL server binaries not found (Debian: apt-get install postgresql)")
    data_dir = cluster_dir(data_dir)
    if not (data_dir / "PG_VERSION").exists():
        data_dir.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:
            shutil.chown(data_dir, _RUN_AS, _RUN_AS)
            data_dir.chmod(0o700)
        _run(
            [str(bindir / "initdb"), "-D", str(data_dir), "-U", ROLE, "--auth=trust", "-E", "UTF8"],
            f"{data_dir}: initdb",
        )
    options = [f"-p {port}", f"-k {data_dir}", "-c listen_addresses=127.0.0.1", "-c max_connections=300"]
    options += [f"-c {k}={v}" for k, v in (settings or {}).items()]
    _run(
        [str(bindir / "pg_ctl"), "-D", str(data_dir), "-l", str(data_dir / "server.log"), "-w", "-t", "60"]
        + ["-o", " ".join(options), "start"],
        f"{data_dir}: pg_ctl start (see {data_dir / 'server.log'})",
    )
    for name in (DATABASE, MLFLOW_DATABASE):
        exists = _run(
            [str(bindir / "psql"), "-h", "127.0.0.1", "-p", str(port), "-U", ROLE, "-d", "postgres", "-tAc"]
            + [f"SELECT 1 FROM pg_database WHERE datname = '{name}'"],
            f"127.0.0.1:{port}: psql",
        )
        if exists.stdout.strip() != "1":
            _run(
                [str(bindir / "createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", ROLE, name],
                f"127.0.0.1:{port}: createdb {name}",
            )
    return url(port)


def stop(data_dir: Path) -> None:
    """Stop the server of cluster `data_dir` (fast shutdown: open sessions are rolled back)."""
    bindir = find_bindir()
    if bindir is None:
        raise DatabaseError("PostgreSQL server binaries not found (Debian: apt-get install postgresql)")
    _run(
        [str(bindir / "pg_ctl"), "-D", str(data_dir.resolve()), "-m", "fast", "-w", "stop"],
        f"{data_dir}: stop",
    )


def _default_dir() -> Path:
    from pipeline.core.config import repo_root

    return repo_root() / DEFAULT_DIR


def _cmd(args: argparse.Namespace) -> int:
    data_dir = args.dir if args.dir is not None else _default_dir()
    if args.action == "start":
        address = start(data_dir, args.port)
        where = data_dir.resolve()
        kept = (
            f" (kept in {where}: the {_RUN_AS} user cannot enter {data_dir.parent})"
            if where != data_dir.absolute()
            else ""
        )
        print(f"PostgreSQL running in {data_dir}{kept} at {address}")
        print(f"  export FTCAL_OPTUNA_STORAGE={address}")
        backend = url(args.port, database=MLFLOW_DATABASE).replace("postgresql://", "postgresql+psycopg://")
        print(f"  mlflow server --backend-store-uri {backend} --artifacts-destination ./mlartifacts")
    else:
        stop(data_dir)
        print(f"PostgreSQL of {data_dir} stopped")
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal db start|stop [DIR]`."""
    parser = subparsers.add_parser(
        "db", help="start or stop a local PostgreSQL server", description=(__doc__ or "").split("\n\n")[0]
    )
    parser.add_argument("action", choices=("start", "stop"))
    parser.add_argument(
        "dir",
        nargs="?",
        type=Path,
        default=None,
        help=f"cluster directory (default: {DEFAULT_DIR} at the repo root)",
    )
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"TCP port on 127.0.0.1 (default {DEFAULT_PORT})"
    )
    parser.set_defaults(func=_cmd)
