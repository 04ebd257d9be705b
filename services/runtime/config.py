"""The one config loader: a TOML file whose tables name ``onboard.contracts.params`` sections.

Example (``deploy/config/archer.toml``)::

    [safety]
    wheel_torque_max = 1.5

Unknown sections or fields and wrongly typed values are errors, reported with the
file name, before any service starts.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from onboard.contracts.params import SECTIONS, with_overrides


IDENTIFIED_SECTIONS = ("estimator", "control")  # each reads archer identify's robot (robot_description/identified.py)


class ConfigError(ValueError):
    pass


def load_params(path: str | Path | None, sections: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Parameter objects for ``sections`` (all when None), overridden by ``path``."""
    wanted = sections if sections is not None else tuple(SECTIONS)
    params = {name: SECTIONS[name]() for name in wanted}
    if path is None:
        return params
    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: {exc}") from None
    identified = {section: data[section].get("identified", "") for section in IDENTIFIED_SECTIONS if isinstance(data.get(section), dict)}
    if len(set(identified.values())) > 1 or len(identified) == 1 and any(identified.values()):
        # the estimator places the CoM by it and the low level's balance observer must not count it again
        raise ConfigError(f"{path}: archer identify's file goes in both [estimator] and [control] identified, the same; got {identified}")
    for section, overrides in data.items():
        if section not in SECTIONS:
            raise ConfigError(f"{path}: unknown section [{section}]; known: {', '.join(sorted(SECTIONS))}")
        if not isinstance(overrides, dict):
            raise ConfigError(f"{path}: [{section}] must be a table")
        if section in params:
            try:
                params[section] = with_overrides(params[section], overrides)
            except ValueError as exc:
                raise ConfigError(f"{path}: [{section}] {exc}") from None
    return params
