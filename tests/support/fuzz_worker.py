"""Fuzz worker: reads one input per request line and reports how the readers behaved.

Run by :mod:`fuzzing` as a persistent subprocess.  Each request is a JSON line ``{"path": ...}``;
each answer a JSON line ``{"outcome": ..., "detail": ...}`` where the outcome is

* ``ok``: every ping read and every value in its documented range;
* ``error``: a :class:`sonarmap.errors.SonarmapError` (the only acceptable failure);
* ``foreign``: any other exception (a defect);
* ``bad_value``: a ping came back with a value outside its documented range (a defect);
* ``memory``: the case needed more than the address-space headroom (``MemoryError``).

The address space is capped at the size after start-up plus ``--headroom-mb`` so that a case which
allocates more fails here instead of taking the machine down.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import traceback
import warnings

import numpy as np

INT64_MAX = 2**63 - 1


def _vm_size_bytes() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


def check_ping(ping: object) -> str | None:
    """Why ``ping`` is outside its documented range, or None."""
    from sonarmap.ping import Ping

    if not isinstance(ping, Ping):
        return f"not a Ping: {type(ping).__name__}"
    img = ping.image
    if img.dtype != np.float32 or img.ndim != 2:
        return f"image dtype/ndim {img.dtype}/{img.ndim}"
    if img.shape != ping.geometry.shape:
        return f"image shape {img.shape} != geometry {ping.geometry.shape}"
    if img.size and not np.isfinite(img).all():
        return "image not finite"
    if img.size and (float(img.min()) < 0.0 or float(img.max()) > 1.0 + 1e-6):
        return f"image outside [0, 1]: {float(img.min())}..{float(img.max())}"
    if not isinstance(ping.time_ns, int) or not 0 <= ping.time_ns <= INT64_MAX:
        return f"time_ns {ping.time_ns!r}"
    g = ping.geometry
    r = np.asarray(g.range_m, dtype=np.float64)
    az = np.asarray(g.azimuth_rad, dtype=np.float64)
    if not (np.isfinite(r).all() and np.isfinite(az).all()):
        return "geometry not finite"
    if r.size and (r.min() < 0.0 or r.max() > 25_000.0):
        return f"range {r.min()}..{r.max()} m"
    if az.size and np.abs(az).max() > np.pi + 1e-9:
        return f"azimuth beyond pi: {np.abs(az).max()}"
    if ping.pose is not None:
        if not (np.isfinite(ping.pose.position_m).all() and np.isfinite(ping.pose.orientation_xyzw).all()):
            return "pose not finite"
    return None


def run_case(path: str, max_pings: int) -> dict[str, str]:
    from sonarmap.errors import SonarmapError
    from sonarmap.io import detect_format, format_module, read_pings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            n = 0
            for ping in read_pings(path):
                why = check_ping(ping)
                if why is not None:
                    return {"outcome": "bad_value", "detail": why}
                n += 1
                if n >= max_pings:
                    break
            fmt = detect_format(path)
            if fmt != "pngjson":
                count = format_module(fmt).count_pings(path)
                if not isinstance(count, int) or count < 0:
                    return {"outcome": "bad_value", "detail": f"count_pings {count!r}"}
        return {"outcome": "ok", "detail": f"{n} pings"}
    except SonarmapError as exc:
        return {"outcome": "error", "detail": " ".join(str(exc).split())[:300]}
    except MemoryError:
        return {"outcome": "memory", "detail": "MemoryError"}
    except RecursionError as exc:
        return {"outcome": "foreign", "detail": f"RecursionError: {str(exc)[:200]}"}
    except Exception as exc:  # noqa: BLE001 - classifying is the point
        tb = traceback.extract_tb(exc.__traceback__)
        where = f"{tb[-1].filename.rsplit('/', 1)[-1]}:{tb[-1].lineno}" if tb else "?"
        return {"outcome": "foreign", "detail": f"{type(exc).__name__} at {where}: {str(exc)[:200]}"}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--headroom-mb", type=int, default=1024)
    ap.add_argument("--max-pings", type=int, default=64)
    args = ap.parse_args()
    # Import what the readers need before capping the address space.
    import sonarmap.io  # noqa: F401
    from sonarmap.io import _modules

    _modules()
    limit = _vm_size_bytes() + args.headroom_mb * 1024 * 1024
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    sys.stdout.write(json.dumps({"ready": True}) + "\n")
    sys.stdout.flush()
    for line in sys.stdin:
        req = json.loads(line)
        res = run_case(req["path"], args.max_pings)
        sys.stdout.write(json.dumps(res) + "\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
