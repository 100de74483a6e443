"""Gains files (JSON), shared by `afbl reproduce --gains`, `afbl montecarlo --gains`, tuning.

Format (channel order phi, theta, psi, z):
    {"controller": "afbl", "gamma": [4 floats], "k": [4 floats], "lambda": [4 floats]}
    {"controller": "afbl_paper", "gamma": [...], "k": [...]}
    {"controller": "fbl", "P": [...], "I": [...], "D": [...]}
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from .controllers import CONTROLLERS, AbstractController

# file key -> controller field
_FILE_KEYS = {
    "fbl": {"P": "P", "I": "I", "D": "D"},
    "afbl": {"gamma": "gamma", "k": "k", "lambda": "lam"},
    "afbl_paper": {"gamma": "gamma", "k": "k"},
}


def gains_to_dict(controller: AbstractController) -> dict:
    """The gains-file dictionary of a controller."""
    keys = _FILE_KEYS[controller.name]
    out: dict = {"controller": controller.name}
    for file_key, field in keys.items():
        out[file_key] = [float(x) for x in getattr(controller, field)]
    return out


def controller_from_dict(data: dict, source: str = "gains") -> AbstractController:
    """Validate a gains dictionary and build its controller; errors say what is wrong."""
    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a JSON object, got {type(data).__name__}.")
    name = data.get("controller")
    if name not in _FILE_KEYS:
        raise ValueError(
            f"{source}: unknown controller {name!r}; allowed: {', '.join(_FILE_KEYS)}."
        )
    keys = _FILE_KEYS[name]
    unknown = set(data) - set(keys) - {"controller"}
    missing = set(keys) - set(data)
    if unknown or missing:
        raise ValueError(
            f"{source}: controller {name!r} needs keys {', '.join(keys)}"
            + (f"; missing {', '.join(sorted(missing))}" if missing else "")
            + (f"; unknown {', '.join(sorted(unknown))}" if unknown else "")
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
            if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
                raise ValueError(f"{source}: {file_key!r} has a non-numeric entry {x!r}.")
            if x <= 0:
                raise ValueError(f"{source}: {file_key!r} must be positive, got {value!r}.")
        gains[field] = [float(x) for x in value]
    return CONTROLLERS[name](**gains)


def load_gains(path: str | Path) -> AbstractController:
    """Read a gains file (see module docstring) into a controller."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"gains file {path} does not exist.") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"gains file {path} is not valid JSON: {err}.") from None
    return controller_from_dict(data, source=str(path))


def save_gains(controller: AbstractController, path: str | Path) -> None:
    Path(path).write_text(json.dumps(gains_to_dict(controller), indent=2) + "\n")
