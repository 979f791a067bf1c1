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

One validator serves the loader and the nodes: :data:`DESIGN_PARAMETERS` lists every
design key with the type the nodes declare it with (nodes/common.py builds its
descriptors from it, and rclpy enforces them), and :func:`design_from_parameters` checks
those types first, as rclpy would, so a file the nodes refuse (an offset written ``0``,
an integer in ``l0_m``) is refused by ``flexure-ctrl solve`` too, with the same words.
The loader reads the file's scalars as rcl's parameter parser does (:func:`read_parameter_file`).
"""

from dataclasses import dataclass
import enum
import math
import os
from pathlib import Path
import re
import sys
from typing import Any, Dict, Mapping, Optional, Tuple, Union

from flexure_ctrl.core.errors import DesignFileError, one_line, yaml_problem
import numpy as np
import yaml

BRANCHES = ('above', 'below')
PROVENANCES = ('synthetic', 'measured')
TABLE_KEYS = ('l0_m', 'x_f_m', 'y_f_m', 'theta_f_rad')
GEOMETRY_KEYS = ('link1_length_m', 'link1_offset_m', 'link2_length_m', 'link2_offset_m')
MIN_TABLE_POINTS = 4

PathLike = Union[str, os.PathLike]


class ParameterKind(enum.Enum):
    """The type of a design parameter, as a node declares it (a ROS parameter type)."""

    STRING = 'string'
    BOOL = 'bool'
    DOUBLE = 'double'
    DOUBLE_ARRAY = 'double_array'


@dataclass(frozen=True)
class DesignParameter:
    """One design parameter: its dotted name, its type and what it holds (with units)."""

    name: str
    kind: ParameterKind
    description: str


# Every design key, in the order the nodes declare them. The only list: the nodes' ROS
# parameter descriptors are built from it.
DESIGN_PARAMETERS: Tuple[DesignParameter, ...] = (
    (DesignParameter('design.name', ParameterKind.STRING, 'design name'),
     DesignParameter('design.description', ParameterKind.STRING, 'what the design is'),
     DesignParameter('design.provenance', ParameterKind.STRING, 'synthetic or measured'),
     DesignParameter('design.provenance_note', ParameterKind.STRING,
                     'how the table was made'),
     DesignParameter('design.recommended', ParameterKind.BOOL, 'false for designs to avoid'),
     DesignParameter('design.warning', ParameterKind.STRING,
                     'why a design is not recommended'),
     DesignParameter('design.branch', ParameterKind.STRING, 'above or below'),
     DesignParameter('design.stroke_limit_m', ParameterKind.DOUBLE,
                     'symmetric actuator stroke limit (m)'))
    + tuple(DesignParameter(f'design.table.{key}', ParameterKind.DOUBLE_ARRAY,
                            'characterisation table column (m or rad)')
            for key in TABLE_KEYS)
    + tuple(DesignParameter(f'design.table_joint_2.{key}', ParameterKind.DOUBLE_ARRAY,
                            "joint 2's own table column (m or rad), if the joints differ; "
                            'optional')
            for key in TABLE_KEYS)
    + tuple(DesignParameter(f'design.geometry.{key}', ParameterKind.DOUBLE,
                            'link geometry (m)')
            for key in GEOMETRY_KEYS))


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


def installed_prefix() -> Optional[Path]:
    """
    Return this interpreter's prefix (``sys.prefix``) if flexure_ctrl's data is there.

    tools/setup.sh links the package's data files (the ament index marker, package.xml,
    ``config/``) into ``<venv>/share`` as a colcon install would; None when they are not.
    """
    prefix = Path(sys.prefix)
    marker = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'flexure_ctrl'
    return prefix if marker.exists() else None


def ensure_ament_prefix_path() -> None:
    """
    Set ``AMENT_PREFIX_PATH`` to :func:`installed_prefix` when it is unset or empty.

    So the entry points work from the venv without ``source tools/env.sh``: the ament
    index (and every process started from here, which inherits the variable) finds the
    message packages and flexure_ctrl in the venv. A set variable is left alone.
    """
    if os.environ.get('AMENT_PREFIX_PATH'):
        return
    prefix = installed_prefix()
    if prefix is not None:
        os.environ['AMENT_PREFIX_PATH'] = str(prefix)


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
    if not os.environ.get('AMENT_PREFIX_PATH'):
        # tools/env.sh not sourced: the ament index would raise; look in our own prefix.
        prefix = installed_prefix()
        if prefix is not None:
            dirs.append(prefix / 'share' / 'flexure_ctrl' / 'config')
        return dirs
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
    return design_from_parameters(_ros_parameters(read_parameter_file(path), path), path)


class _RclLoader(yaml.SafeLoader):
    """
    A YAML loader that types plain scalars as rcl's parameter parser does.

    A quoted scalar is a string. A plain one is a bool if it is one of rcl's words
    (``y``, ``yes``, ``true``, ``on`` ... in lower, title or upper case), else an integer
    if C's ``strtol`` (base 0) reads all of it (``12``, ``0x1f``, ``017``), else a double
    if ``strtod`` does (``1.5``, ``1e-3``, ``.5``, ``inf``), else a string. So a file
    means the same to :func:`load_design` as to a node (PyYAML alone reads ``1e-3`` as a
    string and ``1_000.0`` as a number; rcl the other way round). Keys are strings.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        """Build a mapping whose keys are the keys' text (``y:`` is the name ``y``)."""
        mapping = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                raise yaml.constructor.ConstructorError(
                    'while reading a mapping', node.start_mark,
                    'found a key that is not a name', key_node.start_mark)
            mapping[key_node.value] = self.construct_object(value_node, deep=deep)
        return mapping


_RclLoader.yaml_implicit_resolvers = {}
_RCL_TRUE = ('y', 'yes', 'true', 'on')
_RCL_FALSE = ('n', 'no', 'false', 'off')
_RCL_BOOL_WORDS = {variant: value for words, value in ((_RCL_TRUE, True), (_RCL_FALSE, False))
                   for word in words for variant in (word, word.title(), word.upper())}
_RCL_INT = re.compile(r'^[-+]?(?:0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)$')
_RCL_DOUBLE = re.compile(
    r'^[-+]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?'
    r'|0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)(?:[pP][-+]?[0-9]+)?'
    r'|(?i:inf|infinity|nan))$')
_RclLoader.add_implicit_resolver(
    'tag:yaml.org,2002:bool',
    re.compile('^(?:' + '|'.join(map(re.escape, _RCL_BOOL_WORDS)) + ')$'), None)
_RclLoader.add_implicit_resolver('tag:yaml.org,2002:int', _RCL_INT, None)
_RclLoader.add_implicit_resolver('tag:yaml.org,2002:float', _RCL_DOUBLE, None)


def _rcl_int(text: str) -> int:
    """``strtol(text, NULL, 0)`` of a text that :data:`_RCL_INT` matched."""
    sign, digits = (-1, text[1:]) if text[0] == '-' else (1, text.lstrip('+'))
    if digits[:2] in ('0x', '0X'):
        return sign * int(digits[2:], 16)
    return sign * int(digits, 8 if digits.startswith('0') and len(digits) > 1 else 10)


def _rcl_double(text: str) -> float:
    """``strtod(text, NULL)`` of a text that :data:`_RCL_DOUBLE` matched."""
    unsigned = text.lstrip('+-')
    if unsigned[:2] in ('0x', '0X'):
        value = float.fromhex(unsigned)
        return -value if text.startswith('-') else value
    return float(text)


_RclLoader.add_constructor(
    'tag:yaml.org,2002:bool',
    lambda loader, node: _RCL_BOOL_WORDS[loader.construct_scalar(node)])
_RclLoader.add_constructor(
    'tag:yaml.org,2002:int', lambda loader, node: _rcl_int(loader.construct_scalar(node)))
_RclLoader.add_constructor(
    'tag:yaml.org,2002:float', lambda loader, node: _rcl_double(loader.construct_scalar(node)))


def read_parameter_file(path: PathLike) -> Any:
    """
    Read a ROS parameter file as rcl does (see :class:`_RclLoader`).

    :raises DesignFileError: the file cannot be read or is not valid YAML (one line that
        names the file and, for YAML, the line and column).
    """
    try:
        with open(path, encoding='utf-8') as stream:
            return yaml.load(stream, Loader=_RclLoader)  # a SafeLoader, typed as rcl types
    except OSError as error:
        raise DesignFileError(path, '<file>',
                              f'cannot read: {error.strerror or one_line(error)}') from error
    except yaml.YAMLError as error:
        raise DesignFileError(path, '<file>', yaml_problem(error)) from error


def holds_design(path: PathLike) -> bool:
    """
    Return whether the parameter file at ``path`` sets any ``design.`` parameter.

    A file that cannot be read or parsed holds none.
    """
    try:
        document = read_parameter_file(path)
    except DesignFileError:
        return False
    if not isinstance(document, Mapping):
        return False
    for section in document.values():
        parameters = section.get('ros__parameters') if isinstance(section, Mapping) else None
        if isinstance(parameters, Mapping) and any(
                name == 'design' or name.startswith('design.')
                for name in _flatten(parameters)):
            return True
    return False


def _ros_parameters(document: Any, path: PathLike) -> Mapping:
    """Return the ``ros__parameters`` mapping of a one-node ROS parameter file."""
    if not isinstance(document, Mapping) or not document:
        raise DesignFileError(path, '/**', 'expected a ROS parameter file (/**: ros__parameters:)')
    node_key = '/**' if '/**' in document else next(iter(document))
    node = document[node_key]
    if not isinstance(node, Mapping) or 'ros__parameters' not in node:
        raise DesignFileError(path, f'{node_key}.ros__parameters', 'missing')
    parameters = node['ros__parameters']
    if not isinstance(parameters, Mapping):
        raise DesignFileError(path, f'{node_key}.ros__parameters',
                              f'expected a mapping of parameters, got {_shown(parameters)}')
    return parameters


def _flatten(parameters: Mapping, prefix: str = '') -> Dict[str, Any]:
    """
    Return the parameters of a nested mapping by their dotted names, as rcl names them.

    An empty list is left out: rcl leaves such a parameter unset.
    """
    flat: Dict[str, Any] = {}
    for key, value in parameters.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            flat.update(_flatten(value, f'{name}.'))
        elif not (isinstance(value, (list, tuple)) and len(value) == 0):
            flat[name] = value
    return flat


def _shown(value: Any) -> str:
    """Show a value as an error message does: ``0 (int)``."""
    return f'{value!r} ({type(value).__name__})'


def _float_problem(value: Any) -> Optional[str]:
    """Why ``value`` is not a double parameter's value (an int is not); None if it is."""
    if isinstance(value, float):
        return None
    if isinstance(value, int) and not isinstance(value, bool):
        return f'expected a float (write {float(value)!r}), got {_shown(value)}'
    return f'expected a float, got {_shown(value)}'


def type_problem(kind: ParameterKind, value: Any) -> Optional[str]:
    """
    Say why rclpy would refuse ``value`` for a parameter of ``kind``; None if it would not.

    rclpy types a parameter by how the file writes it and never converts: a double must be
    written as a float (``0.0``, not ``0``), and a double array must hold floats only.
    """
    if kind is ParameterKind.DOUBLE:
        return _float_problem(value)
    if kind is ParameterKind.DOUBLE_ARRAY:
        if not isinstance(value, (list, tuple, np.ndarray)):
            return f'expected a list of numbers written as floats, got {_shown(value)}'
        for index, item in enumerate(value):
            problem = _float_problem(item)
            if problem is not None:
                return f'entry {index}: {problem}'
        return None
    if kind is ParameterKind.BOOL:
        return None if isinstance(value, bool) else \
            f'expected true or false, got {_shown(value)}'
    return None if isinstance(value, str) else f'expected a string, got {_shown(value)}'


def check_design_types(parameters: Mapping, path: PathLike = '<memory>') -> None:
    """
    Refuse, as rclpy refuses it for a node, a design value of another type than declared.

    :param parameters: the ``ros__parameters`` mapping (nested, or by dotted names).
    :raises DesignFileError: naming the file, the first bad key (in declaration order) and
        its value.
    """
    flat = _flatten(parameters)
    for parameter in DESIGN_PARAMETERS:
        if parameter.name in flat:
            problem = type_problem(parameter.kind, flat[parameter.name])
            if problem is not None:
                raise DesignFileError(path, parameter.name, problem)


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
    """
    Build a validated :class:`Design` from the ``ros__parameters`` mapping.

    The types first, as rclpy checks them for a node (:func:`check_design_types`), then the
    values: present, finite, positive where needed, tables strictly increasing.
    """
    check_design_types(parameters, path)
    reader = _KeyReader(_flatten(parameters), path)
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

    def __init__(self, flat: Mapping, path: PathLike):
        """Read the parameters ``flat`` (by dotted name) of the file ``path``."""
        self._flat = flat
        self._path = path

    def _get(self, dotted: str, default: Any = _MISSING) -> Any:
        if dotted in self._flat:
            return self._flat[dotted]
        if default is not self._MISSING:
            return default
        raise DesignFileError(self._path, dotted, 'missing')

    def _fail(self, dotted: str, problem: str):
        raise DesignFileError(self._path, dotted, problem)

    def has(self, dotted: str) -> bool:
        """Return whether any key of the section ``dotted`` is present (optional sections)."""
        return any(name.startswith(f'{dotted}.') for name in self._flat)

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
        if not isinstance(value, (list, tuple, np.ndarray)) or len(value) == 0:
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
