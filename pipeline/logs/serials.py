"""Sensor serial numbers in a log's experiment record: which physical FT boards it was recorded with.

One key per sensor, ``serial.<sensor>: <serial>``: in the MCAP ``experiment`` metadata record, and for a
``.mat`` file or a dataDumper run in its sidecar YAML (`pipeline.logs.sidecar`), e.g.
``serial.l_leg_ft: FT45-2041``. The simulator writes ``robot.serials`` of params.yaml into every log;
`pipeline.export.identity` records them at export and checks them on the logs a calibration is run on.
"""

from __future__ import annotations

from collections.abc import Mapping

KEY = "serial."  # experiment record key prefix: serial.<sensor>


def log_serials(experiment: Mapping[str, object] | None) -> dict[str, str]:
    """Sensor -> serial of the ``serial.<sensor>`` keys of an experiment record (empty values ignored)."""
    return {
        str(k)[len(KEY) :]: str(v).strip()
        for k, v in (experiment or {}).items()
        if str(k).startswith(KEY) and str(v).strip()
    }


def serial_record(serials: Mapping[str, str] | None) -> dict[str, str]:
    """The experiment record's keys for `serials` (sensor -> serial)."""
    return {f"{KEY}{sensor}": str(serial) for sensor, serial in (serials or {}).items()}
