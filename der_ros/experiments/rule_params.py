"""The frozen parameters of the exit's rule baselines in ``config/baselines.yaml``: IDM+MOBIL
(``mobil``) and SUMO's model with tuned lane-change parameters (``sumo_tuned``).

Both are tuned per scenario on the *tuning* evaluation seeds (``research/tuning/exit_rules.py``) and
frozen here by network name, beside the gap rule's thresholds (:func:`der_ros.experiments.baselines.
load_gap_params`)::

    mobil:
      exit: {exit_bias: 4.0, safe_decel: 4.0}      # MobilParams fields; the others keep their defaults
    sumo_tuned:
      exit: {lcAssertive: 3.0, lcCooperative: 1.0}  # SUMO LC2013 parameters of the ego

A missing or malformed section is one :class:`ConfigError` line naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

from der_ros.configuration import ConfigError, read_yaml_mapping
from sumo_bridge.mobil import MobilParams
from sumo_bridge.scenario import LANE_CHANGE_PARAMS

__all__ = ["MOBIL_FIELDS", "load_mobil_params", "load_sumo_tuned_params", "lane_change_entries"]

#: the MobilParams fields config/baselines.yaml may set (the IDM is the ego vType's, not set here)
MOBIL_FIELDS = ("politeness", "threshold", "safe_decel", "exit_bias", "exit_lookahead")
#: MobilParams fields that must be >= 0 (politeness may be negative: Treiber's "malicious" drivers)
_NON_NEGATIVE = ("threshold", "safe_decel", "exit_bias", "exit_lookahead")


def _section(path: Path, baseline: str, network: str, expected: str) -> dict[str, Any]:
    data = read_yaml_mapping(path, expected="a mapping of baselines")
    group = data.get(baseline)
    if group is not None and not isinstance(group, dict):
        raise ConfigError(f"{path}: {baseline} = {group!r}, expected a mapping of networks")
    section = (group or {}).get(network)
    if not isinstance(section, dict):
        raise ConfigError(f"{path}: {baseline}.{network} missing, expected a mapping of {expected}")
    return section


def _number(path: Path, key: str, value: Any) -> float:
    try:
        number = math.nan if isinstance(value, bool) else float(value)
    except (TypeError, ValueError):
        number = math.nan
    if not math.isfinite(number):
        raise ConfigError(f"{path}: {key} = {value!r}, expected a finite number")
    return number


def load_mobil_params(network: str, path: str | Path) -> MobilParams:
    """The tuned :class:`MobilParams` of ``network`` (section ``mobil.<network>``)."""
    path = Path(path)
    section = _section(path, "mobil", network, f"MobilParams fields ({', '.join(MOBIL_FIELDS)})")
    unknown = sorted(set(section) - set(MOBIL_FIELDS))
    if unknown:
        raise ConfigError(f"{path}: mobil.{network}: unknown keys {unknown}, expected some of {', '.join(MOBIL_FIELDS)}")
    values = {k: _number(path, f"mobil.{network}.{k}", v) for k, v in section.items()}
    for k in _NON_NEGATIVE:
        if values.get(k, 0.0) < 0.0:
            raise ConfigError(f"{path}: mobil.{network}.{k} = {values[k]!r}, expected a value >= 0")
    if values.get("exit_lookahead", 1.0) == 0.0:
        raise ConfigError(f"{path}: mobil.{network}.exit_lookahead = 0.0, expected a value > 0 (metres)")
    return dataclasses.replace(MobilParams(), **values)


def load_sumo_tuned_params(network: str, path: str | Path) -> dict[str, float]:
    """The ego's tuned SUMO lane-change parameters of ``network`` (section ``sumo_tuned.<network>``),
    sorted by name."""
    path = Path(path)
    section = _section(path, "sumo_tuned", network, f"SUMO lane-change parameters ({', '.join(LANE_CHANGE_PARAMS)})")
    unknown = sorted(set(section) - set(LANE_CHANGE_PARAMS))
    if unknown:
        raise ConfigError(f"{path}: sumo_tuned.{network}: unknown keys {unknown}, expected SUMO lane-change "
                          f"parameters ({', '.join(LANE_CHANGE_PARAMS)})")  # fmt: skip
    if not section:
        raise ConfigError(f"{path}: sumo_tuned.{network} is empty, expected at least one lane-change parameter")
    values = {k: _number(path, f"sumo_tuned.{network}.{k}", v) for k, v in sorted(section.items())}
    for k, v in values.items():
        if v < 0.0 or (k == "lcAssertive" and v == 0.0):  # SUMO divides the gaps it needs by lcAssertive
            raise ConfigError(f"{path}: sumo_tuned.{network}.{k} = {v!r}, expected a value "
                              f"{'> 0' if k == 'lcAssertive' else '>= 0'}")  # fmt: skip
    return values


def lane_change_entries(params: dict[str, float]) -> list[str]:
    """``{'lcAssertive': 3.0}`` as ScenarioConfig.ego_lane_change_params entries (``['lcAssertive=3.0']``)."""
    return [f"{k}={v!r}" for k, v in sorted(params.items())]
