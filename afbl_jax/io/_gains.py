"""Gains files (JSON): the one gains schema of every file the package reads or writes.

Format (channel order phi, theta, psi, z; full float64 precision both ways):
    {"controller": "afbl", "gamma": [4 floats], "k": [4 floats], "lambda": [4 floats]}
    {"controller": "afbl_paper", "gamma": [...], "k": [...]}
    {"controller": "fbl", "P": [...], "I": [...], "D": [...]}

Read them with JAX's 64-bit mode on (the ``afbl`` command switches it on before reading
anything); with it off, gains are float32 and `controller_from_dict` refuses values that would
change.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..model import CONTROLLERS, AbstractController

GAINS_SCHEMA: dict[str, dict[str, str]] = {
    "fbl": {"P": "P", "I": "I", "D": "D"},
    "afbl": {"gamma": "gamma", "k": "k", "lambda": "lam"},
    "afbl_paper": {"gamma": "gamma", "k": "k"},
}
"""controller name -> {file key: controller field}."""


def gains_to_dict(controller: AbstractController) -> dict:
    """The gains-file dictionary of a controller (floats at full precision)."""
    keys = GAINS_SCHEMA[controller.name]
    out: dict = {"controller": controller.name}
    for file_key, field in keys.items():
        out[file_key] = [float(x) for x in np.asarray(getattr(controller, field))]
    return out


def _finite_number(x) -> bool:
    """A finite int or float (not a bool; an int too large for a float is not finite)."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


def controller_from_dict(data: dict, source: str = "gains") -> AbstractController:
    """Validate a gains dictionary and build its controller; errors say what is wrong and what
    is allowed."""
    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a JSON object, got {type(data).__name__}.")
    name = data.get("controller")
    if name not in GAINS_SCHEMA:
        raise ValueError(
            f"{source}: unknown controller {name!r}; allowed: {', '.join(GAINS_SCHEMA)}."
        )
    keys = GAINS_SCHEMA[name]
    unknown = set(data) - set(keys) - {"controller"}
    missing = set(keys) - set(data)
    if unknown or missing:
        raise ValueError(
            f"{source}: controller {name!r} needs keys {', '.join(keys)}"
            + (f"; missing {', '.join(sorted(missing))}" if missing else "")
            + (f"; unknown {', '.join(sorted(map(str, unknown)))}" if unknown else "")
            + "."
        )
    gains = {}
    for file_key, field in keys.items():
        value = data[file_key]
        if not isinstance(value, list) or len(value) != 4:
            raise ValueError(
                f"{source}: {file_key!r} must be a list of 4 numbers (phi, theta, psi, z), "
                f"got {value!r}."
            )
        for x in value:
            if not _finite_number(x):
                raise ValueError(
                    f"{source}: {file_key!r} has a non-numeric or non-finite entry {x!r}; "
                    "gains are finite numbers > 0."
                )
            if x <= 0:
                raise ValueError(f"{source}: {file_key!r} must be positive, got {value!r}.")
        gains[field] = [float(x) for x in value]
    controller = CONTROLLERS[name](**gains)
    for field, want in gains.items():
        got = np.asarray(getattr(controller, field), dtype=np.float64)
        if not np.array_equal(got, np.asarray(want)):
            raise ValueError(
                f"{source}: {field} {want} cannot be represented in JAX's "
                f"{getattr(controller, field).dtype} (got {got.tolist()}); enable 64-bit mode "
                "(jax.config.update('jax_enable_x64', True)) before reading gains."
            )
    return controller


def load_gains(path: str | Path) -> AbstractController:
    """Read a gains file (see module docstring) into a controller."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"gains file {path} does not exist.") from None
    except IsADirectoryError:
        raise ValueError(f"gains file {path} is a directory, not a JSON file.") from None
    except ValueError as err:  # syntax, encoding, integers too long to convert
        raise ValueError(f"gains file {path} is not valid JSON: {err}.") from None
    except RecursionError:
        raise ValueError(f"gains file {path} is nested too deeply to parse.") from None
    except OSError as err:
        raise ValueError(f"gains file {path} cannot be read: {err.strerror}.") from None
    return controller_from_dict(data, source=str(path))


def save_gains(controller: AbstractController, path: str | Path) -> None:
    """Write ``controller``'s gains file (see module docstring)."""
    Path(path).write_text(json.dumps(gains_to_dict(controller), indent=2) + "\n")
