"""
Flexure design parameter files: loading and validation.

A design file is a ROS 2 parameter file (``/**: ros__parameters: design: ...``), so
the very same file feeds a node through ``--ros-args --params-file`` and the plain
loader here. It holds one flexure coupling's characterisation table (actuator
extension to flexure tip pose), the two-link geometry, the actuator stroke limit and
the solution branch. Every value is SI: metres and radians.

Loading a bad file raises one :class:`~flexure_ctrl.core.errors.DesignFileError` that
names the file and the dotted key (``design.table.theta_f_rad``), never a bare
``KeyError`` from deep inside.
"""

from dataclasses import dataclass
import math
import os
from pathlib import Path
from typing import Any, Mapping, Optional, Union

from flexure_ctrl.core.errors import DesignFileError
import numpy as np
import yaml

BRANCHES = ('above', 'below')
PROVENANCES = ('synthetic', 'measured')
TABLE_KEYS = ('l0_m', 'x_f_m', 'y_f_m', 'theta_f_rad')
GEOMETRY_KEYS = ('link1_length_m', 'link1_offset_m', 'link2_length_m', 'link2_offset_m')
MIN_TABLE_POINTS = 4

PathLike = Union[str, os.PathLike]


@dataclass(frozen=True)
class CharacterisationData:
    """
    Measured (or modelled) static response of one flexure coupling.

    All arrays have the same length and are sampled at strictly increasing actuator
    extensions ``l0_m``; ``x_f_m``/``y_f_m`` are the flexure tip position in metres in
    the flexure's root frame and ``theta_f_rad`` the tip angle in radians.
    """

    l0_m: np.ndarray
    x_f_m: np.ndarray
    y_f_m: np.ndarray
    theta_f_rad: np.ndarray


@dataclass(frozen=True)
class LinkGeometry:
    """
    Rigid links of the two-link arm, in metres.

    ``link1_length_m``/``link1_offset_m`` place the root of flexure 2 in the frame of
    flexure 1's tip (along the tip direction, and to its left). ``link2_*`` place the
    end-point target in the frame of flexure 2's tip in the same way.
    """

    link1_length_m: float
    link1_offset_m: float
    link2_length_m: float
    link2_offset_m: float


@dataclass(frozen=True)
class Design:
    """One flexure design: its table, the arm geometry and the operating limits."""

    name: str
    description: str
    provenance: str
    provenance_note: str
    recommended: bool
    warning: str
    branch: str
    stroke_limit_m: float
    table: CharacterisationData
    geometry: LinkGeometry
    source_path: Optional[str] = None
    # Joint 2's own table when the two joints differ (a measured design: each joint is
    # characterised on its own); None: joint 2 follows ``table`` too, as in the paper.
    table_joint_2: Optional[CharacterisationData] = None

    def joint_table(self, joint: int) -> CharacterisationData:
        """Return the table of joint 1 or 2."""
        if joint not in (1, 2):
            raise ValueError(f'joint must be 1 or 2, got {joint!r}')
        return self.table_joint_2 if joint == 2 and self.table_joint_2 is not None \
            else self.table


def config_search_dirs() -> list:
    """
    Return the folders searched for configuration files, in order.

    ``FLEXURE_CTRL_CONFIG_DIR`` first (a lab's own files), then the source tree's
    ``config/`` and finally the installed ``share/flexure_ctrl/config``.
    """
    dirs = []
    override = os.environ.get('FLEXURE_CTRL_CONFIG_DIR')
    if override:
        dirs.append(Path(override))
    dirs.append(Path(__file__).resolve().parents[2] / 'config')
    try:
        from ament_index_python.packages import get_package_share_directory
        from ament_index_python.packages import PackageNotFoundError
    except ImportError:
        return dirs
    try:
        share = Path(get_package_share_directory('flexure_ctrl'))
    except (PackageNotFoundError, ValueError, LookupError):
        return dirs
    dirs.append(share / 'config')
    return dirs


def find_config_file(relative: PathLike) -> Path:
    """Return the first existing ``<config dir>/<relative>``; raise FileNotFoundError."""
    for folder in config_search_dirs():
        path = folder / relative
        if path.is_file():
            return path
    raise FileNotFoundError(
        f'{relative} not found in {", ".join(str(d) for d in config_search_dirs())}')


def design_search_dirs() -> list:
    """Return the folders searched for ``<name>.yaml`` designs: ``designs/`` of each config dir."""
    return [folder / 'designs' for folder in config_search_dirs()]


def available_designs() -> list:
    """Names of the designs found in :func:`design_search_dirs`, sorted."""
    names = set()
    for folder in design_search_dirs():
        if folder.is_dir():
            names.update(p.stem for p in folder.glob('*.yaml'))
    return sorted(names)


def find_design_file(name_or_path: PathLike) -> Path:
    """Resolve a design name (``cfa``) or a path to an existing design file."""
    candidate = Path(name_or_path)
    if candidate.suffix in ('.yaml', '.yml') or candidate.parent != Path('.'):
        if candidate.is_file():
            return candidate
        raise DesignFileError(candidate, '<file>', 'no such file')
    for folder in design_search_dirs():
        path = folder / f'{name_or_path}.yaml'
        if path.is_file():
            return path
    known = ', '.join(available_designs()) or 'none found'
    raise DesignFileError(
        f'{name_or_path}.yaml', '<file>',
        f'no design named {str(name_or_path)!r}; known designs: {known}')


def load_design(name_or_path: PathLike) -> Design:
    """
    Load and validate a design by name or path.

    :raises DesignFileError: the file is missing, not YAML, or any key is missing or bad.
    """
    path = find_design_file(name_or_path)
    try:
        with open(path, encoding='utf-8') as stream:
            document = yaml.safe_load(stream)
    except OSError as error:
        raise DesignFileError(path, '<file>', f'cannot read: {error}') from error
    except yaml.YAMLError as error:
        raise DesignFileError(path, '<file>', f'not valid YAML: {error}') from error
    return design_from_parameters(_ros_parameters(document, path), path)


def _ros_parameters(document: Any, path: PathLike) -> Mapping:
    """Return the ``ros__parameters`` mapping of a one-node ROS parameter file."""
    if not isinstance(document, Mapping) or not document:
        raise DesignFileError(path, '/**', 'expected a ROS parameter file (/**: ros__parameters:)')
    node_key = '/**' if '/**' in document else next(iter(document))
    node = document[node_key]
    if not isinstance(node, Mapping) or 'ros__parameters' not in node:
        raise DesignFileError(path, f'{node_key}.ros__parameters', 'missing')
    return node['ros__parameters']


def _read_table(reader: '_KeyReader', prefix: str, path: PathLike) -> CharacterisationData:
    """Read and check one characterisation table under ``prefix`` (e.g. ``design.table``)."""
    table = CharacterisationData(*(reader.float_array(f'{prefix}.{key}')
                                   for key in TABLE_KEYS))
    lengths = {key: len(getattr(table, key)) for key in TABLE_KEYS}
    if len(set(lengths.values())) != 1:
        raise DesignFileError(path, prefix, f'arrays must have equal lengths, got {lengths}')
    if lengths['l0_m'] < MIN_TABLE_POINTS:
        raise DesignFileError(path, f'{prefix}.l0_m',
                              f'needs at least {MIN_TABLE_POINTS} points')
    for key in ('l0_m', 'theta_f_rad'):
        steps = np.diff(getattr(table, key))
        if np.any(steps <= 0.0):
            first = int(np.argmax(steps <= 0.0))
            raise DesignFileError(
                path, f'{prefix}.{key}',
                f'must be strictly increasing, but entry {first + 1} does not exceed entry '
                f'{first}')
    return table


def design_from_parameters(parameters: Mapping, path: PathLike = '<memory>') -> Design:
    """Build a validated :class:`Design` from the ``ros__parameters`` mapping."""
    reader = _KeyReader(parameters, path)
    table = _read_table(reader, 'design.table', path)
    table_joint_2 = None
    if reader.has('design.table_joint_2'):
        table_joint_2 = _read_table(reader, 'design.table_joint_2', path)
    stroke = reader.positive_float('design.stroke_limit_m')
    for prefix, checked in (('design.table', table), ('design.table_joint_2', table_joint_2)):
        if checked is not None and (-stroke < checked.l0_m[0] or stroke > checked.l0_m[-1]):
            raise DesignFileError(
                path, 'design.stroke_limit_m',
                f'stroke +-{stroke} m reaches outside the table {prefix} '
                f'[{checked.l0_m[0]}, {checked.l0_m[-1]}] m')
    geometry = LinkGeometry(
        link1_length_m=reader.positive_float('design.geometry.link1_length_m'),
        link1_offset_m=reader.finite_float('design.geometry.link1_offset_m'),
        link2_length_m=reader.positive_float('design.geometry.link2_length_m'),
        link2_offset_m=reader.finite_float('design.geometry.link2_offset_m'))
    return Design(
        name=reader.string('design.name'),
        description=reader.string('design.description', default=''),
        provenance=reader.choice('design.provenance', PROVENANCES),
        provenance_note=reader.string('design.provenance_note', default=''),
        recommended=reader.boolean('design.recommended', default=True),
        warning=reader.string('design.warning', default=''),
        branch=reader.choice('design.branch', BRANCHES),
        stroke_limit_m=stroke,
        table=table,
        geometry=geometry,
        source_path=str(path),
        table_joint_2=table_joint_2)


class _KeyReader:
    """Typed access to dotted keys that reports the file and key on any problem."""

    _MISSING = object()

    def __init__(self, parameters: Mapping, path: PathLike):
        self._parameters = parameters
        self._path = path

    def _get(self, dotted: str, default: Any = _MISSING) -> Any:
        node: Any = self._parameters
        for part in dotted.split('.'):
            if not isinstance(node, Mapping) or part not in node:
                if default is not self._MISSING:
                    return default
                raise DesignFileError(self._path, dotted, 'missing')
            node = node[part]
        return node

    def _fail(self, dotted: str, problem: str):
        raise DesignFileError(self._path, dotted, problem)

    def has(self, dotted: str) -> bool:
        """Return whether the key is present (for optional sections)."""
        return self._get(dotted, None) is not None

    def string(self, dotted: str, default: Any = _MISSING) -> str:
        value = self._get(dotted, default)
        if not isinstance(value, str):
            self._fail(dotted, f'expected a string, got {value!r}')
        return value

    def boolean(self, dotted: str, default: Any = _MISSING) -> bool:
        value = self._get(dotted, default)
        if not isinstance(value, bool):
            self._fail(dotted, f'expected true or false, got {value!r}')
        return value

    def choice(self, dotted: str, choices: tuple) -> str:
        value = self.string(dotted)
        if value not in choices:
            self._fail(dotted, f'expected one of {list(choices)}, got {value!r}')
        return value

    def finite_float(self, dotted: str) -> float:
        value = self._get(dotted)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self._fail(dotted, f'expected a number, got {value!r}')
        if not math.isfinite(value):
            self._fail(dotted, f'must be finite, got {value!r}')
        return float(value)

    def positive_float(self, dotted: str) -> float:
        value = self.finite_float(dotted)
        if value <= 0.0:
            self._fail(dotted, f'must be positive, got {value!r}')
        return value

    def float_array(self, dotted: str) -> np.ndarray:
        value = self._get(dotted)
        if not isinstance(value, list) or not value:
            self._fail(dotted, f'expected a non-empty list of numbers, got {value!r}')
        for index, item in enumerate(value):
            if isinstance(item, bool) or not isinstance(item, (int, float)):
                self._fail(dotted, f'entry {index} is not a number: {item!r}')
            if not math.isfinite(item):
                self._fail(dotted, f'entry {index} is not finite: {item!r}')
        return np.asarray(value, dtype=float)


def design_to_parameters(design: Design) -> dict:
    """Return the ``ros__parameters`` mapping that :func:`design_from_parameters` reads."""
    table = design.table
    geometry = design.geometry
    parameters = {
        'design': {
            'name': design.name,
            'description': design.description,
            'provenance': design.provenance,
            'provenance_note': design.provenance_note,
            'recommended': design.recommended,
            'warning': design.warning,
            'branch': design.branch,
            'stroke_limit_m': float(design.stroke_limit_m),
            'table': {key: [float(v) for v in getattr(table, key)] for key in TABLE_KEYS},
            'geometry': {key: float(getattr(geometry, key)) for key in GEOMETRY_KEYS},
        }
    }
    if design.table_joint_2 is not None:
        parameters['design']['table_joint_2'] = {
            key: [float(v) for v in getattr(design.table_joint_2, key)] for key in TABLE_KEYS}
    return parameters


def nest_dotted(flat: Mapping) -> dict:
    """
    Turn ROS-style dotted parameter names into the nested mapping of the file.

    ``{'design.table.l0_m': [...]}`` becomes ``{'design': {'table': {'l0_m': [...]}}}``,
    which :func:`design_from_parameters` reads; this is how a node that received a design
    through ``--params-file`` builds the same :class:`Design` as :func:`load_design`.
    """
    nested: dict = {}
    for dotted, value in flat.items():
        node = nested
        *parents, leaf = dotted.split('.')
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = list(value) if isinstance(value, (list, tuple)) else value
    return nested
