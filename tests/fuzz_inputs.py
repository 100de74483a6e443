"""A seeded generator of bad distribution and gains files (each one invalid by construction).

Every file starts from a valid override (random sections and keys of the default distribution,
or a random controller's gains) and gets one mutation that makes it invalid: unknown names,
wrong types, reversed or out-of-domain ranges, non-finite or huge numbers, broken syntax,
non-UTF-8 bytes, deep nesting, cross-key conflicts. `bad_files` writes them and says what each
mutation was (for the assertion message).
"""

from __future__ import annotations

import json
import random
from pathlib import Path

from afbl_jax.io import GAINS_SCHEMA
from afbl_jax.studies.montecarlo import DEFAULT_DISTRIBUTION

RANGE_KEYS = [
    (s, k)
    for s, body in DEFAULT_DISTRIBUTION.items()
    for k, v in body.items()
    if isinstance(v, list) and s != "unmodeled"
]
POSITIVE_KEYS = [
    ("turbulence", "airspeed"),
    ("turbulence", "altitude"),
    ("turbulence", "omega_min"),
    ("time", "t1"),
]
BOOL_KEYS = [("pulses", "enabled"), ("gust", "enabled"), ("turbulence", "enabled")]
STRICT_LOWER = {  # key -> a low value outside its domain
    ("model_error", "inertia_scale"): 0.0,
    ("model_error", "thrust_coefficient_scale"): -0.5,
    ("model_error", "thrust_to_weight"): 0.9,
    ("payload", "fraction"): -1.5,
    ("gust", "buildup_time"): 0.0,
    ("pulses", "duration"): -0.1,
    ("aero", "drag_coefficient"): -0.2,
    ("initial", "attitude"): -1.3,
}


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if v != v:
            return "nan"
        if v in (float("inf"), float("-inf")):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def to_toml(doc: dict) -> str:
    lines = []
    for section, body in doc.items():
        if not isinstance(body, dict):
            lines.insert(0, f"{json.dumps(section)} = {_toml_value(body)}")
            continue
        lines.append(f"[{json.dumps(section)}]")
        lines += [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in body.items()]
    return "\n".join(lines) + "\n"


def _valid_distribution(rng: random.Random) -> dict:
    """A few valid overrides (values inside their domains)."""
    doc: dict = {}
    for section, key in rng.sample(RANGE_KEYS, 2):
        lo, hi = DEFAULT_DISTRIBUTION[section][key]
        doc.setdefault(section, {})[key] = [lo, hi]
    return doc


def _bad_distribution(rng: random.Random) -> tuple[str, str, bytes]:
    """(suffix, what, contents) of one invalid distribution file."""
    doc = _valid_distribution(rng)
    section, key = rng.choice(RANGE_KEYS)
    kind = rng.choice(
        [
            "unknown section",
            "unknown key",
            "range type",
            "reversed range",
            "non-finite",
            "below domain",
            "probabilities",
            "bool",
            "int key",
            "positive key",
            "section not a table",
            "top level",
            "syntax",
            "huge int",
            "deep nesting",
            "t1 before events",
            "choice",
            "digital only",
            "not utf-8",
        ]
    )
    suffix = rng.choice([".toml", ".json"])
    body = doc.setdefault(section, {})
    if kind == "unknown section":
        doc[rng.choice(["payloads", "wind", "Payload", "pay\nload", ""])] = {"fraction": [0, 1]}
    elif kind == "unknown key":
        body[rng.choice(["fractions", "scale", "k\ney", "", "FRACTION"])] = [0.0, 1.0]
    elif kind == "range type":
        body[key] = rng.choice(["0.1", True, {"low": 0.1}, [0.1], [0.1, 0.2, 0.3], [0.1, "x"]])
    elif kind == "reversed range":
        lo, hi = DEFAULT_DISTRIBUTION[section][key]
        body[key] = [hi + 1.0, lo]
    elif kind == "non-finite":
        body[key] = [rng.choice([float("nan"), float("-inf")]), rng.choice([1.0, float("inf")])]
    elif kind == "below domain":
        (section, key), low = rng.choice(list(STRICT_LOWER.items()))
        doc.setdefault(section, {})[key] = [low, max(low, 0.0) + 1.5]
    elif kind == "probabilities":
        doc["turbulence"] = {
            "intensity_probabilities": rng.choice(
                [{"light": 0.5}, {"light": 1.5, "severe": -0.5}, {"calm": 1.0}, [0.5, 0.5]]
            )
        }
    elif kind == "bool":
        s, k = rng.choice(BOOL_KEYS)
        doc[s] = {k: rng.choice([1, "true", "yes", 0.0])}
    elif kind == "int key":
        doc["turbulence"] = {"n_frequencies": rng.choice([0, -3, 2.5, "32", True])}
    elif kind == "positive key":
        s, k = rng.choice(POSITIVE_KEYS)
        doc[s] = {k: rng.choice([0, -1.0, "5", [1.0]])}
    elif kind == "section not a table":
        doc[section] = rng.choice([3, "x", [1, 2]])
    elif kind == "top level":
        suffix = ".json"
        return suffix, kind, json.dumps(rng.choice([[1, 2], 3, "payload", None, True])).encode()
    elif kind == "syntax":
        text = to_toml(doc) if suffix == ".toml" else json.dumps(doc)
        cut = rng.randrange(1, max(2, len(text) - 1))
        return suffix, kind, (text[:cut] + rng.choice(["[", "= =", "{", "\x00"])).encode()
    elif kind == "huge int":
        suffix = ".json"
        if rng.random() < 0.5:
            body[key] = [10**400, 10**401]
        else:  # more digits than Python converts by default
            return suffix, kind, ('{"payload": {"fraction": [0, 1' + "0" * 5000 + "]}}").encode()
    elif kind == "deep nesting":
        suffix = ".json"
        depth = 200_000
        return suffix, kind, ("[" * depth + "]" * depth).encode()
    elif kind == "t1 before events":
        doc["time"] = {"t1": 1.0}  # pulses and gusts start up to 16 s by default
    elif kind == "choice":
        doc["unmodeled"] = {"enabled": True, "plant": rng.choice(["rigid", "", 3])}
    elif kind == "digital only":
        doc["unmodeled"] = {"enabled": True, "control_rate": [0.0, 0.0], "noise_angle": [0, 0.01]}
    elif kind == "not utf-8":
        return suffix, kind, b"\xff\xfe\x00[payload]\x80\x81"
    if suffix == ".toml":
        return suffix, kind, to_toml(doc).encode()
    return suffix, kind, json.dumps(doc).encode()


def _bad_gains(rng: random.Random) -> tuple[str, bytes]:
    """(what, contents) of one invalid gains file."""
    name = rng.choice(list(GAINS_SCHEMA))
    doc = {"controller": name, **{k: [1.0, 2.0, 3.0, 4.0] for k in GAINS_SCHEMA[name]}}
    key = rng.choice(list(GAINS_SCHEMA[name]))
    kind = rng.choice(
        [
            "controller",
            "missing key",
            "extra key",
            "length",
            "entry type",
            "not positive",
            "non-finite",
            "huge int",
            "top level",
            "syntax",
            "deep nesting",
            "not utf-8",
        ]
    )
    if kind == "controller":
        doc["controller"] = rng.choice(["lqr", "FBL", "", None, 3])
    elif kind == "missing key":
        del doc[key]
    elif kind == "extra key":
        doc[rng.choice(["kp", "Gamma", "lam"])] = [1, 1, 1, 1]
    elif kind == "length":
        doc[key] = rng.choice([[1.0] * 3, [1.0] * 5, [], 1.0])
    elif kind == "entry type":
        doc[key] = [1.0, 2.0, rng.choice(["3", True, None, [3.0]]), 4.0]
    elif kind == "not positive":
        doc[key] = [1.0, rng.choice([0, -2.5, -1e-300]), 3.0, 4.0]
    elif kind == "non-finite":
        text = json.dumps(doc).replace("2.0", rng.choice(["NaN", "Infinity", "-Infinity", "1e400"]))
        return kind, text.encode()
    elif kind == "huge int":
        if rng.random() < 0.5:
            doc[key] = [1.0, 10**400, 3.0, 4.0]
        else:  # more digits than Python converts by default
            text = json.dumps(doc).replace("2.0", "2" + "0" * 5000, 1)
            return kind, text.encode()
    elif kind == "top level":
        return kind, json.dumps(rng.choice([[doc], "afbl", 3, None])).encode()
    elif kind == "syntax":
        text = json.dumps(doc)
        return kind, text[: rng.randrange(1, len(text) - 1)].encode()
    elif kind == "deep nesting":
        return kind, ('{"a":' * 100_000 + "1" + "}" * 100_000).encode()
    elif kind == "not utf-8":
        return kind, b"\xff\xfe{\x00\x80"
    return kind, json.dumps(doc).encode()


def bad_files(folder: Path, seed: int, n_distribution: int, n_gains: int):
    """Write the files; returns [(kind "distribution" | "gains", path, what)]."""
    rng = random.Random(seed)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n_distribution):
        suffix, what, data = _bad_distribution(rng)
        path = folder / f"dist_{i:03d}{suffix}"
        path.write_bytes(data)
        out.append(("distribution", path, what))
    for i in range(n_gains):
        what, data = _bad_gains(rng)
        path = folder / f"gains_{i:03d}.json"
        path.write_bytes(data)
        out.append(("gains", path, what))
    return out
