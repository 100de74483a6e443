"""The Monte-Carlo case distribution: written once here, overridable from a TOML or JSON file.

A distribution file has the same sections and keys as `DEFAULT_DISTRIBUTION`; every key it
gives replaces the default, every key it leaves out keeps the default. A range ``[low, high]``
is sampled uniformly (``[x, x]`` fixes the value). Probability tables are categorical
distributions (non-negative weights summing to 1). Unknown sections or keys, ranges with
high < low, and values outside their physical domain raise `ValueError` naming the key.
"""

from __future__ import annotations

import copy
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...model import AERODYNAMIC_MODELS
from ...scenario import (
    ROUGHNESS_LENGTH,
    TURBULENCE_INTENSITIES,
    turbulence_edges,
    turbulence_grid,
)

MEAN_WIND_CAP = 8.0
"""Top of the default mean-wind speed range [m/s] at the turbulence altitude: below the flight
envelope boundary of the distribution's mid-range vehicle with its mean payload (the envelope
status flags the cases that still cannot be flown: high drag, heavy payload and a gust)."""

DEFAULT_DISTRIBUTION: dict = {
    "payload": {
        "fraction": [0.0, 0.5],  # p, true mass (1 + p) m
        "attach_time": [0.0, 0.0],  # [s]; 0 = carried from the start, e.g. [5, 15] mid-flight
    },
    "model_error": {  # true vehicle = nominal model x these factors
        "inertia_scale": [0.9, 1.1],  # Ix, Iy, Iz
        "thrust_coefficient_scale": [0.9, 1.1],  # b
        "drag_coefficient_scale": [0.9, 1.1],  # d (rotor yaw-torque coefficient)
        "thrust_to_weight": [2.5, 2.5],  # omega_max set for this ratio at nominal mass and b
    },
    "aero": {  # afbl_jax.model aerodynamics; model shared by all cases, coefficients per case
        "model": "rotor_drag",  # "rotor_drag" (H-force at the hubs + parasitic) or "linear"
        "drag_coefficient": [0.1, 0.3],  # linear drag c_d [N s/m] ("linear")
        "cp_offset": [0.0, 0.03],  # centre of pressure of the body drag above the CoM [m]
        # rotor drag ("rotor_drag"): from the Hummingbird's identified values (RotorPy) up to
        # those scaled to Table 1's larger rotors (k ~ R^3, c_D ~ arm^2; docs/paper_notes.md)
        "rotor_drag_horizontal": [1.19e-4, 4.34e-4],  # k_d [N / ((rad/s) (m/s))]
        "rotor_drag_vertical": [2.32e-4, 8.47e-4],  # k_z [N / ((rad/s) (m/s))]
        "parasitic_drag_horizontal": [5.0e-3, 9.15e-3],  # c_D body x, y [N / (m/s)^2]
        "parasitic_drag_vertical": [1.0e-2, 1.83e-2],  # c_D body z [N / (m/s)^2]
        "hub_height": [0.0, 0.05],  # rotor hubs above the centre of mass [m]
    },
    "flight": {  # how the vehicle flies the case
        # true: an outer position loop (afbl_jax.PositionHold) holds / steers the horizontal
        # position around the inner attitude loops, as real multirotors fly; false: no
        # position loop, roll and pitch follow attitude references and the vehicle drifts
        # with the air
        "position_hold": True,
        # "trimmed": the case starts in equilibrium with its mean wind (trim attitude, rotor
        # speeds, controller states); "rest": level, at rest, zero controller states
        "start": "trimmed",
        "kp": 1.92,  # position loop gains [1/s^2], [1/s], [1/s^3] (x and y)
        "kd": 2.4,
        "ki": 0.512,
        "tilt_max": 0.7,  # tilt limit of the position loop's command [rad]
        "filter_frequency": 10.0,  # attitude command filter natural frequency [rad/s]
        "windup_time": 1.0,  # anti-windup back-calculation time constant [s]
    },
    "envelope": {  # flight envelope: what a trim must leave for control (afbl_jax.EnvelopeLimits)
        "tilt": 0.6,  # largest trim tilt [rad]
        "rotor_reserve": 0.2,  # fraction of each rotor's top thrust kept at trim
    },
    "pulses": {  # the paper's rectangular disturbance pulses
        "enabled": True,
        "torque": [-0.02, 0.02],  # [N m], each of phi, theta, psi
        "vertical_force": [-3.0, 3.0],  # [N]
        "start": [2.0, 16.0],  # [s], torque and force pulse sampled independently
        "duration": [0.2, 2.0],  # [s]
    },
    "gust": {  # one MIL-F-8785C 1-cosine gust per case (u, v, w along the mean wind)
        "enabled": True,
        # "turbulence": magnitude per axis = sigma_multiple x sigma sqrt(2 (1 - rho(d_m))), tied
        # to the gust length d_m = airspeed x build-up time, the Dryden scale length and sigma;
        # "independent": magnitudes drawn from the amplitude ranges below
        "magnitude": "turbulence",
        "sigma_multiple": [1.0, 3.0],  # standard deviations of the velocity change ("turbulence")
        "horizontal_amplitude": [0.0, 6.0],  # |A_u|, |A_v| [m/s] ("independent"), random sign
        "vertical_amplitude": [0.0, 2.0],  # |A_w| [m/s] ("independent"), random sign
        "buildup_time": [0.5, 3.0],  # per axis [s]
        "start": [2.0, 16.0],  # [s]
    },
    "mean_wind": {  # steady wind at the altitude
        "enabled": True,
        # "speed": drawn uniformly from the speed range below; "w20": W20 of the case's
        # turbulence level (turbulence.intensity = "table") through the MIL-F-8785C
        # low-altitude log profile
        "source": "speed",
        "speed": [0.0, MEAN_WIND_CAP],  # mean-wind speed at the altitude [m/s] ("speed")
        "direction": [-3.141592653589793, 3.141592653589793],  # azimuth it blows towards [rad]
    },
    "turbulence": {  # Dryden, MIL-HDBK-1797 low altitude, sum of sinusoids
        "enabled": True,
        # "mean_wind": intensities from the case's own mean wind (sigma_w = 0.1 W20, W20 from
        # the log profile), a continuous range of intensities; "table": a level drawn from
        # intensity_probabilities (light / moderate / severe: W20 = 15 / 30 / 45 knots)
        "intensity": "mean_wind",
        "intensity_probabilities": {"none": 0.0, "light": 0.5, "moderate": 0.35, "severe": 0.15},
        # [m/s] carrying the frozen field; 0 = the case's mean airspeed (position hold: the
        # mean-wind speed; drifting with the air: 0), at least min_airspeed
        "airspeed": 0.0,
        "min_airspeed": 1.0,  # [m/s]
        "altitude": 10.0,  # [m] of the turbulence and of the mean wind
        "n_frequencies": 64,
        "omega_min": 0.0005,  # [rad/s]
        "omega_max": 300.0,  # [rad/s], top of the log-spaced grid of n_frequencies cells
        # [rad/s]: lines above it are left out (phases still drawn for all n_frequencies, so a
        # case keeps its lines below); 100 rad/s is well past the attitude loop's bandwidth
        "omega_cutoff": 100.0,
    },
    "initial": {  # perturbation added to the start (trimmed or at rest)
        "attitude": [0.0, 0.0],  # phi, theta, psi at t0 [rad]
        "rate": [0.0, 0.0],  # their rates [rad/s]
    },
    # position hold: "hold" (station keeping, yaw and altitude steps) and "waypoints" (position
    # steps besides); without it the attitude profiles "step" and "sine"
    "reference": {"profile_probabilities": {"hold": 0.5, "waypoints": 0.5}},
    "time": {"t1": 20.0},  # [s], runs start at t0 = 0
    "unmodeled": {  # afbl_jax.UnmodeledDynamics per case; off = the paper's closed loop
        "enabled": False,
        "plant": "paper",  # "paper" (eq. 15) or "full" (rigid body), shared by all cases
        "motor_tau": [0.0, 0.0],  # rotor time constant tau_m [s]; 0 = instantaneous
        "control_rate": [0.0, 0.0],  # controller rate f_c [Hz]; [0, 0] = continuous controller
        "delay_samples": [0, 0],  # measurement delay [whole samples], integers, inclusive
        "noise_angle": [0.0, 0.0],  # std of measured phi, theta, psi [rad]
        "noise_rate": [0.0, 0.0],  # std of measured angle rates [rad/s]
        "noise_altitude": [0.0, 0.0],  # std of measured z [m]
        "noise_vertical_speed": [0.0, 0.0],  # std of measured zd [m/s]
    },
}

ATTITUDE_PROFILES = ("step", "sine")
"""Reference profiles without a position loop (the paper's attitude steps and sines)."""
POSITION_PROFILES = ("hold", "waypoints")
"""Reference profiles with a position loop (`afbl_jax.scenario.mission_reference`)."""

# key -> (kind, lower bound or None, bound inclusive?)
_RANGE_RULES = {
    ("payload", "fraction"): (-1.0, False),
    ("payload", "attach_time"): (0.0, True),
    ("model_error", "inertia_scale"): (0.0, False),
    ("model_error", "thrust_coefficient_scale"): (0.0, False),
    ("model_error", "drag_coefficient_scale"): (0.0, False),
    ("model_error", "thrust_to_weight"): (1.0, False),
    ("aero", "drag_coefficient"): (0.0, True),
    ("aero", "cp_offset"): (None, True),
    ("aero", "rotor_drag_horizontal"): (0.0, True),
    ("aero", "rotor_drag_vertical"): (0.0, True),
    ("aero", "parasitic_drag_horizontal"): (0.0, True),
    ("aero", "parasitic_drag_vertical"): (0.0, True),
    ("aero", "hub_height"): (None, True),
    ("pulses", "torque"): (None, True),
    ("pulses", "vertical_force"): (None, True),
    ("pulses", "start"): (0.0, True),
    ("pulses", "duration"): (0.0, True),
    ("gust", "sigma_multiple"): (0.0, True),
    ("gust", "horizontal_amplitude"): (0.0, True),
    ("gust", "vertical_amplitude"): (0.0, True),
    ("gust", "buildup_time"): (0.0, False),
    ("gust", "start"): (0.0, True),
    ("mean_wind", "speed"): (0.0, True),
    ("mean_wind", "direction"): (None, True),
    ("initial", "attitude"): (-1.2, False),
    ("initial", "rate"): (None, True),
    ("unmodeled", "motor_tau"): (0.0, True),
    ("unmodeled", "control_rate"): (0.0, True),
    ("unmodeled", "delay_samples"): (0.0, True),
    ("unmodeled", "noise_angle"): (0.0, True),
    ("unmodeled", "noise_rate"): (0.0, True),
    ("unmodeled", "noise_altitude"): (0.0, True),
    ("unmodeled", "noise_vertical_speed"): (0.0, True),
}
_PROB_RULES = {
    ("turbulence", "intensity_probabilities"): TURBULENCE_INTENSITIES,
    ("reference", "profile_probabilities"): ATTITUDE_PROFILES + POSITION_PROFILES,
}
_BOOL_KEYS = {
    ("flight", "position_hold"),
    ("pulses", "enabled"),
    ("gust", "enabled"),
    ("mean_wind", "enabled"),
    ("turbulence", "enabled"),
    ("unmodeled", "enabled"),
}
_INT_RANGE_KEYS = {("unmodeled", "delay_samples")}
_CHOICE_KEYS = {
    ("unmodeled", "plant"): ("paper", "full"),
    ("aero", "model"): AERODYNAMIC_MODELS,
    ("gust", "magnitude"): ("turbulence", "independent"),
    ("mean_wind", "source"): ("speed", "w20"),
    ("turbulence", "intensity"): ("mean_wind", "table"),
    ("flight", "start"): ("trimmed", "rest"),
}
_NONNEGATIVE_KEYS = {("turbulence", "airspeed"), ("turbulence", "min_airspeed")}
_POSITIVE_KEYS = {
    ("flight", "kp"),
    ("flight", "kd"),
    ("flight", "ki"),
    ("flight", "filter_frequency"),
    ("flight", "windup_time"),
    ("turbulence", "altitude"),
    ("turbulence", "omega_min"),
    ("turbulence", "omega_max"),
    ("turbulence", "omega_cutoff"),
    ("time", "t1"),
}
_INT_KEYS = {("turbulence", "n_frequencies")}
# key -> (low, high, low inclusive?): numbers in (low, high) or [low, high)
_INTERVAL_KEYS = {
    ("flight", "tilt_max"): (0.0, math.pi / 2, False),
    ("envelope", "tilt"): (0.0, math.pi / 2, False),
    ("envelope", "rotor_reserve"): (0.0, 1.0, True),
}


def turbulence_lines(turb: dict):
    """The turbulence lines a ``[turbulence]`` section realises: (omega_k [rad/s] of the lines
    at or below ``omega_cutoff``, their K + 1 cell edges [rad/s]); the grid is
    `turbulence_grid` over [omega_min, omega_max] in ``n_frequencies`` cells."""
    omega, _ = turbulence_grid(turb["n_frequencies"], turb["omega_min"], turb["omega_max"])
    edges = turbulence_edges(turb["n_frequencies"], turb["omega_min"], turb["omega_max"])
    keep = int(np.sum(omega <= turb["omega_cutoff"]))
    return omega[:keep], edges[: keep + 1]


def _is_number(x) -> bool:
    """A finite int or float (not a bool; an int too large for a float is not finite)."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


def _validate(spec: dict, source: str) -> None:
    if not isinstance(spec, dict):
        raise ValueError(
            f"{source}: expected a table/object of sections, got {type(spec).__name__}."
        )
    for section, body in spec.items():
        if section not in DEFAULT_DISTRIBUTION:
            raise ValueError(
                f"{source}: unknown section [{section}]; allowed: "
                f"{', '.join(DEFAULT_DISTRIBUTION)}."
            )
        if not isinstance(body, dict):
            raise ValueError(f"{source}: [{section}] must be a table of keys, got {body!r}.")
        for key, value in body.items():
            where = f"{source}: {section}.{key}"
            if key not in DEFAULT_DISTRIBUTION[section]:
                raise ValueError(
                    f"{where} is not a known key; allowed in [{section}]: "
                    f"{', '.join(DEFAULT_DISTRIBUTION[section])}."
                )
            k = (section, key)
            if k in _RANGE_RULES:
                if (
                    not isinstance(value, list | tuple)
                    or len(value) != 2
                    or not all(_is_number(v) for v in value)
                ):
                    raise ValueError(
                        f"{where} must be a range [low, high] of two finite numbers, got {value!r}."
                    )
                lo, hi = value
                if hi < lo:
                    raise ValueError(
                        f"{where} = {list(value)} is a negative range "
                        "(high < low); write [low, high]."
                    )
                bound, inclusive = _RANGE_RULES[k]
                if bound is not None and (lo < bound or (lo == bound and not inclusive)):
                    rel = ">=" if inclusive else ">"
                    raise ValueError(f"{where} = {list(value)}: values must be {rel} {bound}.")
                if k in _INT_RANGE_KEYS and not all(
                    isinstance(v, int) or float(v).is_integer() for v in value
                ):
                    raise ValueError(f"{where} = {list(value)}: values must be whole numbers.")
            elif k in _CHOICE_KEYS:
                if value not in _CHOICE_KEYS[k]:
                    raise ValueError(
                        f"{where} must be one of {', '.join(_CHOICE_KEYS[k])}, got {value!r}."
                    )
            elif k in _PROB_RULES:
                names = _PROB_RULES[k]
                if not isinstance(value, dict) or set(value) - set(names):
                    raise ValueError(
                        f"{where} must be a table with keys from {', '.join(names)}, got {value!r}."
                    )
                if not all(_is_number(v) and v >= 0 for v in value.values()):
                    raise ValueError(f"{where}: probabilities must be numbers >= 0, got {value!r}.")
                if not math.isclose(sum(value.values()), 1.0, abs_tol=1e-9):
                    raise ValueError(
                        f"{where}: probabilities must sum to 1, got {sum(value.values())}."
                    )
            elif k in _BOOL_KEYS:
                if not isinstance(value, bool):
                    raise ValueError(f"{where} must be true or false, got {value!r}.")
            elif k in _INT_KEYS:
                if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                    raise ValueError(f"{where} must be an integer >= 1, got {value!r}.")
            elif k in _NONNEGATIVE_KEYS:
                if not _is_number(value) or value < 0:
                    raise ValueError(f"{where} must be a finite number >= 0, got {value!r}.")
            elif k in _POSITIVE_KEYS:
                if not _is_number(value) or value <= 0:
                    raise ValueError(f"{where} must be a finite number > 0, got {value!r}.")
            elif k in _INTERVAL_KEYS:
                lo, hi, closed = _INTERVAL_KEYS[k]
                inside = _is_number(value) and (value >= lo if closed else value > lo)
                if not (inside and value < hi):
                    rel = ">=" if closed else ">"
                    raise ValueError(
                        f"{where} must be a number {rel} {lo:g} and < {hi:g}, got {value!r}."
                    )


@dataclass(frozen=True)
class Distribution:
    """A validated case distribution (see `DEFAULT_DISTRIBUTION` for every key and unit).

    Build with `default_distribution`, `load_distribution(path)` or
    ``Distribution.from_dict(overrides)``; ``spec`` is the full, merged specification.
    """

    spec: dict = field(default_factory=lambda: copy.deepcopy(DEFAULT_DISTRIBUTION))
    source: str = "default"

    def __post_init__(self):
        _validate(self.spec, self.source)
        t1 = self.spec["time"]["t1"]
        turb = self.spec["turbulence"]
        if turb["omega_min"] >= turb["omega_max"]:
            raise ValueError(f"{self.source}: turbulence.omega_min must be < omega_max.")
        lowest = turbulence_grid(turb["n_frequencies"], turb["omega_min"], turb["omega_max"])[0][0]
        if turb["omega_cutoff"] < lowest:
            raise ValueError(
                f"{self.source}: turbulence.omega_cutoff {turb['omega_cutoff']} rad/s leaves no "
                f"line; the lowest line is at {lowest:.4g} rad/s."
            )
        if turb["altitude"] <= ROUGHNESS_LENGTH:
            raise ValueError(
                f"{self.source}: turbulence.altitude must exceed the wind profile's roughness "
                f"length {ROUGHNESS_LENGTH:.4f} m, got {turb['altitude']}."
            )
        wind = self.spec["mean_wind"]
        if turb["airspeed"] == 0 and turb["min_airspeed"] <= 0:
            raise ValueError(
                f"{self.source}: turbulence.airspeed = 0 carries the turbulence at the case's mean "
                "airspeed, which may be 0, so turbulence.min_airspeed must be > 0 [m/s]; or set "
                "turbulence.airspeed > 0."
            )
        if wind["source"] == "w20" and turb["intensity"] != "table":
            raise ValueError(
                f'{self.source}: mean_wind.source = "w20" takes W20 from the case\'s turbulence '
                'level, which needs turbulence.intensity = "table".'
            )
        if turb["enabled"] and turb["intensity"] == "mean_wind" and not wind["enabled"]:
            raise ValueError(
                f'{self.source}: turbulence.intensity = "mean_wind" scales the turbulence with '
                "the mean wind, which [mean_wind] enabled = false switches off; set "
                'turbulence.intensity = "table" (levels drawn from intensity_probabilities) or '
                "enable the mean wind."
            )
        flight = self.spec["flight"]
        allowed = POSITION_PROFILES if flight["position_hold"] else ATTITUDE_PROFILES
        probs = self.spec["reference"]["profile_probabilities"]
        wrong = sorted(n for n, p in probs.items() if p > 0 and n not in allowed)
        if wrong:
            mode = "with" if flight["position_hold"] else "without"
            raise ValueError(
                f"{self.source}: reference profiles {', '.join(wrong)} cannot be flown {mode} "
                f"a position loop (flight.position_hold = "
                f"{str(flight['position_hold']).lower()}); allowed: {', '.join(allowed)}."
            )
        if self.spec["envelope"]["tilt"] >= flight["tilt_max"] and flight["position_hold"]:
            raise ValueError(
                f"{self.source}: envelope.tilt ({self.spec['envelope']['tilt']} rad) must be below "
                f"the position loop's tilt limit flight.tilt_max ({flight['tilt_max']} rad), so "
                "that a trimmed vehicle keeps some tilt for control."
            )
        for section, key in (("payload", "attach_time"), ("pulses", "start"), ("gust", "start")):
            if self.spec[section][key][1] >= t1:
                raise ValueError(
                    f"{self.source}: {section}.{key} must lie before time.t1 = "
                    f"{t1} s, got {self.spec[section][key]}."
                )
        unm = self.spec["unmodeled"]
        rate = unm["control_rate"]
        if rate[0] == 0 and rate[1] > 0:
            raise ValueError(
                f"{self.source}: unmodeled.control_rate = {rate}: either [0, 0] "
                "(continuous controller) or a range of rates > 0 [Hz]."
            )
        if rate[1] == 0:
            digital_only = [
                n
                for n in (
                    "delay_samples",
                    "noise_angle",
                    "noise_rate",
                    "noise_altitude",
                    "noise_vertical_speed",
                )
                if unm[n][1] > 0
            ]
            if digital_only:
                raise ValueError(
                    f"{self.source}: unmodeled.{', '.join(digital_only)} need a "
                    "digital controller (unmodeled.control_rate > 0 [Hz])."
                )

    @classmethod
    def from_dict(cls, overrides: dict, source: str = "overrides") -> Distribution:
        """Defaults with ``overrides`` (same sections/keys, partial) applied; validated.

        Overrides that give ``reference.profile_probabilities`` replace the whole table;
        overrides that set ``flight.position_hold = false`` without giving it get the attitude
        profiles {step: 0.5, sine: 0.5}."""
        _validate(overrides, source)
        spec = copy.deepcopy(DEFAULT_DISTRIBUTION)
        for section, body in overrides.items():
            spec[section].update(copy.deepcopy(body))
        turb = overrides.get("turbulence", {})
        table = turb.get("intensity_probabilities")
        default_table = DEFAULT_DISTRIBUTION["turbulence"]["intensity_probabilities"]
        if (
            table is not None
            and table != default_table
            and spec["turbulence"]["intensity"] != "table"
        ):
            raise ValueError(
                f"{source}: turbulence.intensity_probabilities draws a level per case, which "
                'needs turbulence.intensity = "table" (the default, "mean_wind", takes the '
                "intensities from each case's mean wind)."
            )
        given = overrides.get("reference", {}).get("profile_probabilities")
        if given is None and not spec["flight"]["position_hold"]:
            spec["reference"]["profile_probabilities"] = {"step": 0.5, "sine": 0.5}
        return cls(spec, source)

    def __hash__(self) -> int:
        return hash(json.dumps(self.spec, sort_keys=True))

    def to_dict(self) -> dict:
        return copy.deepcopy(self.spec)

    def describe(self) -> str:
        """Markdown table of every section/key/value."""
        lines = ["| section | key | value |", "|---|---|---|"]
        for section, body in self.spec.items():
            for key, value in body.items():
                lines.append(f"| {section} | {key} | {json.dumps(value)} |")
        return "\n".join(lines)


def default_distribution() -> Distribution:
    """The default Monte-Carlo distribution (`DEFAULT_DISTRIBUTION`)."""
    return Distribution()


def load_distribution(path: str | Path) -> Distribution:
    """Read a TOML (``.toml``) or JSON file of overrides; errors name the bad key."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise ValueError(f"distribution file {path} does not exist.") from None
    except IsADirectoryError:
        raise ValueError(
            f"distribution file {path} is a directory; give a .toml or .json file."
        ) from None
    except OSError as err:
        raise ValueError(f"distribution file {path} cannot be read: {err.strerror}.") from None
    try:
        if path.suffix.lower() == ".toml":
            data = tomllib.loads(text.decode())
        else:
            data = json.loads(text)
    except ValueError as err:  # TOML/JSON syntax, encoding, integers too long to convert
        kind = "TOML" if path.suffix.lower() == ".toml" else "JSON (or name it .toml)"
        raise ValueError(
            f"distribution file {path} could not be parsed as {kind}: {err}."
        ) from None
    except RecursionError:
        raise ValueError(f"distribution file {path} is nested too deeply to parse.") from None
    return Distribution.from_dict(data, source=str(path))
