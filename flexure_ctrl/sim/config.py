"""
Simulator configuration: ``config/simulator.yaml`` plus an optional override file.

The override may set any subset of the keys; a key the defaults do not have, or a value
of another type, is an error that names the key (a typo must not silently fall back to
a default on a rig-like run).
"""

import copy
import os
from pathlib import Path
from typing import Any, Mapping, Optional, Union

from flexure_ctrl.core.design import find_config_file
from flexure_ctrl.core.errors import FlexureCtrlError, yaml_problem
import yaml

DEFAULTS_FILE = 'simulator.yaml'

PathLike = Union[str, os.PathLike]


class SimConfigError(FlexureCtrlError, ValueError):
    """The simulator configuration is invalid; the message names the file and key."""


def _read_yaml(path: Path) -> Mapping:
    try:
        with open(path, encoding='utf-8') as stream:
            document = yaml.safe_load(stream) or {}
    except OSError as error:
        raise SimConfigError(f'{path}: cannot read: {error}') from error
    except yaml.YAMLError as error:
        raise SimConfigError(f'{path}: {yaml_problem(error)}') from error
    if not isinstance(document, Mapping):
        raise SimConfigError(f'{path}: expected a mapping of simulator knobs')
    return document


def _merge(base: dict, override: Mapping, path: Path, prefix: str = '') -> None:
    for key, value in override.items():
        dotted = f'{prefix}{key}'
        if key not in base:
            raise SimConfigError(f'{path}: unknown key {dotted!r}')
        default = base[key]
        if isinstance(default, dict):
            if not isinstance(value, Mapping):
                raise SimConfigError(f'{path}: key {dotted!r} must be a mapping')
            _merge(default, value, path, dotted + '.')
            continue
        if isinstance(default, bool) != isinstance(value, bool):
            raise SimConfigError(f'{path}: key {dotted!r} must be true or false')
        if isinstance(default, (int, float)) and not isinstance(default, bool):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise SimConfigError(f'{path}: key {dotted!r} must be a number, got {value!r}')
            value = type(default)(value) if isinstance(default, float) else value
        elif isinstance(default, list):
            # Numeric lists are per-joint or xyz and keep their length; name lists
            # (tracker targets) may be any length.
            names = all(isinstance(item, str) for item in default)
            if not isinstance(value, list) or (not names and len(value) != len(default)):
                raise SimConfigError(
                    f'{path}: key {dotted!r} must be a list of {len(default)} values')
        elif isinstance(default, str) and not isinstance(value, str):
            raise SimConfigError(f'{path}: key {dotted!r} must be a string')
        base[key] = value


def load_sim_config(override: Optional[PathLike] = None,
                    overrides: Optional[Mapping[str, Any]] = None) -> dict:
    """
    Return the simulator knobs: the defaults, then ``override`` file, then ``overrides``.

    :param override: path of a YAML file with any subset of the keys.
    :param overrides: dotted keys set last, e.g. ``{'network.can_port': 30000}``.
    :raises SimConfigError: naming the file and key of an unknown or mistyped value.
    """
    defaults_path = find_config_file(DEFAULTS_FILE)
    config = copy.deepcopy(dict(_read_yaml(defaults_path)))
    if override is not None:
        path = Path(override)
        _merge(config, _read_yaml(path), path)
    for dotted, value in (overrides or {}).items():
        nested: dict = {}
        node = nested
        *parents, leaf = dotted.split('.')
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
        _merge(config, nested, Path('<command line>'))
    return config
