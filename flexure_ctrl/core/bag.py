"""
rosbag2-compatible MCAP bags: write, read, and recover after a crash.

A bag is a folder holding ``metadata.yaml`` and one ``<folder name>_0.mcap`` file, laid out
as rosbag2 (Jazzy, metadata version 9) writes them with its MCAP storage plugin: profile
``ros2``, one ``ros2msg`` schema per message type (the type's ``.msg`` text followed by
every dependency's, see :func:`message_definition`), ``cdr`` messages, and the
publishers' ``offered_qos_profiles`` in each channel's metadata. ``ros2 bag info``,
``ros2 bag play``, Foxglove and the ``rosbags`` library read it.

Crash safety: :class:`BagWriter` closes the MCAP chunk in progress and hands it to the
operating system at least every ``flush_period_s`` (from a thread of its own, so also
when no message arrives), and rewrites ``metadata.yaml`` then, so a writer killed
without warning leaves a folder that is a bag holding every message written up to one
flush period before the kill. :class:`BagReader` reads such a file (no summary, no
footer, maybe half a chunk at the end) up to its last complete record, and
:func:`recover` rewrites it as a complete bag.

This module does not import rclpy: the message definitions come from the ``.msg`` files
under ``share/`` of the ament prefixes, and messages stay serialized (CDR bytes) unless
:meth:`BagReader.decoded` is asked for.
"""

import heapq
import json
import os
from pathlib import Path
import re
import shutil
import struct
import threading
from typing import Any, Dict, Iterable, Iterator, List, Mapping, NamedTuple, Optional
from typing import Sequence, Tuple

from flexure_ctrl import __version__
from flexure_ctrl.core.errors import BagError
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from mcap_ros2.decoder import DecoderFactory
import yaml

METADATA_FILE = 'metadata.yaml'
# rosbag2 Jazzy writes metadata version 9 (QoS policies as lower-case names).
METADATA_VERSION = 9
ROS_DISTRO = 'jazzy'
PROFILE = 'ros2'
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'
STORAGE_IDENTIFIER = 'mcap'
# rmw's "infinite" duration (INT64_MAX ns) as rosbag2 writes it in a QoS profile.
INFINITE_DURATION = {'sec': 9223372036, 'nsec': 854775807}
DEFINITION_SEPARATOR = '=' * 80

_MCAP_MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEADER = struct.Struct('<BQ')
_PRIMITIVE_TYPES = frozenset((
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'))
_TYPE_NAME = re.compile(r'^([A-Za-z][A-Za-z0-9_]*)/(?:(msg)/)?([A-Za-z][A-Za-z0-9_]*)$')
_COMPRESSIONS = {'none': CompressionType.NONE, 'lz4': CompressionType.LZ4,
                 'zstd': CompressionType.ZSTD}


class BagMessage(NamedTuple):
    """One recorded message: its topic and type, times (ns since the epoch), CDR bytes."""

    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes


def default_search_paths() -> List[Path]:
    """Return the ``share/`` folders of the ament prefixes (``AMENT_PREFIX_PATH``)."""
    prefixes = os.environ.get('AMENT_PREFIX_PATH', '')
    return [Path(prefix) / 'share' for prefix in prefixes.split(os.pathsep) if prefix]


def _split_type_name(type_name: str) -> Tuple[str, str]:
    """
    Split ``pkg/msg/Name`` or ``pkg/Name`` into the package and the type.

    :raises BagError: the name is neither.
    """
    match = _TYPE_NAME.match(type_name)
    if match is None:
        raise BagError(f'message type {type_name!r} is not of the form package/msg/Name')
    return match.group(1), match.group(3)


def _field_dependencies(text: str, package: str) -> List[str]:
    """
    Return the message types a ``.msg`` text uses, as ``pkg/Name``, sorted and unique.

    Constants and primitive fields (also bounded strings ``string<=N`` and arrays ``T[]``,
    ``T[N]``, ``T[<=N]``) are skipped; a type without a package is in ``package``.
    """
    dependencies = set()
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith('#'):
            continue
        field_type = stripped.split()[0]
        field_type = field_type.split('[', 1)[0].split('<=', 1)[0]
        if field_type in _PRIMITIVE_TYPES:
            continue
        if '/' in field_type:
            dependency_package, name = _split_type_name(field_type)
        else:
            dependency_package, name = package, field_type
        dependencies.add(f'{dependency_package}/{name}')
    return sorted(dependencies)


def _find_interface_file(package: str, name: str, suffix: str,
                         search_paths: Sequence[Path]) -> Optional[Path]:
    for share in search_paths:
        candidate = Path(share) / package / 'msg' / (name + suffix)
        if candidate.is_file():
            return candidate
    return None


def message_definition(type_name: str, search_paths: Optional[Sequence[Path]] = None) -> str:
    """
    Return the ``ros2msg`` schema text of a message type, as rosbag2 writes it in MCAP.

    That is the type's own ``.msg`` text, then for each dependency (depth first, each
    one once, in sorted order at each level) a line of 80 ``=``, a line
    ``MSG: pkg/Name`` and the dependency's ``.msg`` text.

    :param type_name: e.g. ``geometry_msgs/msg/PointStamped`` (or ``geometry_msgs/PointStamped``).
    :param search_paths: ``share/`` folders to look in; default :func:`default_search_paths`.
    :returns: the schema text.
    :raises BagError: the type, or one of its dependencies, has no ``.msg`` file; the
        message names the type.
    """
    paths = default_search_paths() if search_paths is None else [Path(p) for p in search_paths]
    root_package, root_name = _split_type_name(type_name)
    seen = set()

    def text_of(package: str, name: str, depth: int) -> str:
        if depth > 50:
            raise BagError(f'message type {type_name!r}: dependencies nest too deep')
        path = _find_interface_file(package, name, '.msg', paths)
        if path is None:
            wanted = f'{package}/msg/{name}'
            context = '' if wanted == f'{root_package}/msg/{root_name}' else \
                f' (a dependency of {type_name})'
            raise BagError(
                f'no message definition for {wanted}{context}: {package}/msg/{name}.msg is '
                f'not under any of {", ".join(str(p) for p in paths) or "(no search paths)"}')
        text = path.read_text(encoding='utf-8')
        result = text
        for dependency in _field_dependencies(text, package):
            if dependency in seen:
                continue
            seen.add(dependency)
            dependency_package, dependency_name = dependency.split('/')
            result += (f'\n{DEFINITION_SEPARATOR}\nMSG: {dependency}\n'
                       + text_of(dependency_package, dependency_name, depth + 1))
        return result

    return text_of(root_package, root_name, 0)


def type_description_hash(type_name: str, search_paths: Optional[Sequence[Path]] = None) -> str:
    """
    Return the ``RIHS01_...`` type hash of a message type, or '' if it is not known.

    The hash comes from the type description (``share/<pkg>/msg/<Name>.json``) that the
    ROS build generates beside the ``.msg`` file.
    """
    return _lookup_type_hash(type_name, search_paths)


def _lookup_type_hash(type_name: str, search_paths: Optional[Sequence[Path]]) -> str:
    paths = default_search_paths() if search_paths is None else [Path(p) for p in search_paths]
    try:
        package, name = _split_type_name(type_name)
    except BagError:
        return ''
    path = _find_interface_file(package, name, '.json', paths)
    if path is None:
        return ''
    try:
        hashes = json.loads(path.read_text(encoding='utf-8')).get('type_hashes', [])
    except (OSError, ValueError):
        return ''
    wanted = f'{package}/msg/{name}'
    for entry in hashes:
        if entry.get('type_name') == wanted:
            return str(entry.get('hash_string', ''))
    return ''


def qos_profile(reliability: str = 'reliable', durability: str = 'volatile',
                history: str = 'keep_last', depth: int = 10,
                liveliness: str = 'automatic') -> Dict[str, Any]:
    """
    Build one offered QoS profile in rosbag2's metadata-version-9 form.

    Policies are lower-case names (``reliable``/``best_effort``, ``volatile``/
    ``transient_local``, ``keep_last``/``keep_all``/``unknown``, ...); durations are
    infinite, as a publisher that sets none offers them.
    """
    return {
        'history': history, 'depth': int(depth), 'reliability': reliability,
        'durability': durability, 'deadline': dict(INFINITE_DURATION),
        'lifespan': dict(INFINITE_DURATION), 'liveliness': liveliness,
        'liveliness_lease_duration': dict(INFINITE_DURATION),
        'avoid_ros_namespace_conventions': False,
    }


def dump_qos_profiles(profiles: Sequence[Mapping[str, Any]]) -> str:
    """Return the profiles as the YAML text rosbag2 puts in an MCAP channel's metadata."""
    if not profiles:
        return ''
    return yaml.safe_dump([dict(p) for p in profiles], sort_keys=False,
                          default_flow_style=False).strip()


class _Topic:
    """What the writer keeps about one topic."""

    __slots__ = ('name', 'type_name', 'channel_id', 'offered_qos_profiles',
                 'type_description_hash', 'message_count')

    def __init__(self, name, type_name, channel_id, offered_qos_profiles,
                 type_description_hash):
        self.name = name
        self.type_name = type_name
        self.channel_id = channel_id
        self.offered_qos_profiles = offered_qos_profiles
        self.type_description_hash = type_description_hash
        self.message_count = 0


class BagWriter:
    """
    Write one rosbag2 bag folder (``metadata.yaml`` + ``<name>_0.mcap``).

    Thread-safe: :meth:`write` may run in subscription callbacks while a thread of the
    writer flushes and another thread closes. Use as a context manager or call
    :meth:`close`.
    """

    def __init__(self, folder, *, flush_period_s: float = 0.5,
                 chunk_size_bytes: int = 1 << 20, compression: str = 'none',
                 file_name: Optional[str] = None,
                 search_paths: Optional[Sequence[Path]] = None,
                 custom_data: Optional[Mapping[str, str]] = None) -> None:
        """
        Create the folder, start the MCAP file and write a first ``metadata.yaml``.

        :param folder: bag folder; created, and refused if it exists and is not empty.
        :param flush_period_s: the longest time a written message stays in memory only
            (s); 0 flushes only when a chunk is full and at close.
        :param chunk_size_bytes: a chunk is also closed when it holds this much.
        :param compression: chunk compression, ``none`` (default: cheapest per message),
            ``lz4`` or ``zstd``.
        :param file_name: name of the MCAP file; default ``<folder name>_0.mcap``.
        :param search_paths: ``share/`` folders for the message definitions.
        :param custom_data: string pairs for ``custom_data`` in ``metadata.yaml``.
        :raises BagError: the folder is not empty or cannot be created, or a bad option.
        """
        if compression not in _COMPRESSIONS:
            raise BagError(f'compression must be one of {", ".join(_COMPRESSIONS)}, '
                           f'got {compression!r}')
        if flush_period_s < 0:
            raise BagError(f'flush_period_s must be >= 0, got {flush_period_s}')
        self.folder = Path(folder)
        if self.folder.exists() and (not self.folder.is_dir() or any(self.folder.iterdir())):
            raise BagError(f'bag folder {self.folder} already exists and is not empty')
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise BagError(f'cannot create bag folder {self.folder}: {error}') from error
        self.file_name = file_name or f'{self.folder.name}_0.mcap'
        self.path = self.folder / self.file_name
        self._search_paths = search_paths
        self._custom_data = dict(custom_data) if custom_data else None
        self._compression = compression
        # One lock orders the MCAP writer between callbacks, the flush thread and close().
        self._lock = threading.Lock()
        # Serialises metadata.yaml rewrites (done outside _lock, so writes never wait on
        # the YAML dump).
        self._metadata_lock = threading.Lock()
        self._topics: Dict[str, _Topic] = {}
        self._schema_ids: Dict[str, int] = {}
        self._message_count = 0
        self._start_ns: Optional[int] = None
        self._end_ns: Optional[int] = None
        self._dirty = False
        self._closed = False
        self._stream = open(self.path, 'wb')
        self._mcap = Writer(self._stream, chunk_size=chunk_size_bytes,
                            compression=_COMPRESSIONS[compression])
        self._mcap.start(profile=PROFILE, library=f'flexure_ctrl {__version__}')
        self._mcap.flush()
        self._write_metadata()
        self.flush_period_s = float(flush_period_s)
        self._stop_flushing = threading.Event()
        self._flusher: Optional[threading.Thread] = None
        if self.flush_period_s > 0:
            self._flusher = threading.Thread(target=self._flush_periodically,
                                             name='bag-flush', daemon=True)
            self._flusher.start()

    def __enter__(self) -> 'BagWriter':
        """Return the writer."""
        return self

    def __exit__(self, *exc_info) -> None:
        """Close the bag, also when the block raised."""
        self.close()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` ran."""
        return self._closed

    @property
    def message_count(self) -> int:
        """Messages written so far."""
        return self._message_count

    def topics(self) -> Dict[str, str]:
        """Return the topics added so far, topic -> type name."""
        with self._lock:
            return {name: topic.type_name for name, topic in self._topics.items()}

    def add_topic(self, topic: str, type_name: str,
                  offered_qos_profiles: Optional[Sequence[Mapping[str, Any]]] = None,
                  type_description_hash: Optional[str] = None,
                  definition: Optional[str] = None) -> None:
        """
        Add a topic (an MCAP channel, and the type's schema the first time).

        :param topic: absolute topic name.
        :param type_name: e.g. ``geometry_msgs/msg/PointStamped``.
        :param offered_qos_profiles: the publishers' QoS, see :func:`qos_profile`;
            default one reliable, volatile profile.
        :param type_description_hash: ``RIHS01_...``; default the one the type
            description under ``share/`` gives, or ''.
        :param definition: schema text; default :func:`message_definition` of the type.
        :raises BagError: the topic is already there, the type has no definition, or the
            bag is closed.
        """
        if definition is None:
            definition = message_definition(type_name, self._search_paths)
        if type_description_hash is None:
            type_description_hash = _lookup_type_hash(type_name, self._search_paths)
        profiles = [dict(p) for p in (offered_qos_profiles
                                      if offered_qos_profiles is not None
                                      else [qos_profile()])]
        with self._lock:
            self._check_open()
            if topic in self._topics:
                raise BagError(f'topic {topic} is already in bag {self.folder}')
            schema_id = self._schema_ids.get(type_name)
            if schema_id is None:
                schema_id = self._mcap.register_schema(
                    type_name, SCHEMA_ENCODING, definition.encode('utf-8'))
                self._schema_ids[type_name] = schema_id
            channel_id = self._mcap.register_channel(
                topic, MESSAGE_ENCODING, schema_id,
                {'offered_qos_profiles': dump_qos_profiles(profiles),
                 'topic_type_hash': type_description_hash})
            self._topics[topic] = _Topic(topic, type_name, channel_id, profiles,
                                         type_description_hash)
            self._dirty = True

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: Optional[int] = None) -> None:
        """
        Append one serialized message (cheap: it goes to the chunk in memory).

        :param topic: a topic added with :meth:`add_topic`.
        :param data: the CDR bytes.
        :param log_time_ns: receive time, ns since the epoch.
        :param publish_time_ns: send time, ns since the epoch; default ``log_time_ns``.
        :raises BagError: unknown topic, or the bag is closed.
        """
        if publish_time_ns is None:
            publish_time_ns = log_time_ns
        with self._lock:
            if self._closed:
                raise BagError(f'bag {self.folder} is closed')
            entry = self._topics.get(topic)
            if entry is None:
                raise BagError(f'topic {topic} was not added to bag {self.folder}')
            self._mcap.add_message(entry.channel_id, log_time_ns, data, publish_time_ns,
                                   entry.message_count)
            entry.message_count += 1
            self._message_count += 1
            if self._start_ns is None or log_time_ns < self._start_ns:
                self._start_ns = log_time_ns
            if self._end_ns is None or log_time_ns > self._end_ns:
                self._end_ns = log_time_ns
            self._dirty = True

    def flush(self) -> None:
        """Write the chunk in progress and ``metadata.yaml`` if anything changed."""
        with self._lock:
            if self._closed or not self._dirty:
                return
            self._mcap.flush()
            self._dirty = False
        self._write_metadata()

    def close(self) -> None:
        """Finish the MCAP file (summary, footer) and write the final ``metadata.yaml``."""
        self._stop_flushing.set()
        if self._flusher is not None and self._flusher is not threading.current_thread():
            self._flusher.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._mcap.add_metadata('rosbag2', {
                'serialized_metadata': yaml.safe_dump(
                    self._metadata()['rosbag2_bagfile_information'], sort_keys=False)})
            self._mcap.finish()
            self._stream.flush()
            os.fsync(self._stream.fileno())
            self._stream.close()
        self._write_metadata()

    def _check_open(self) -> None:
        if self._closed:
            raise BagError(f'bag {self.folder} is closed')

    def _flush_periodically(self) -> None:
        while not self._stop_flushing.wait(self.flush_period_s):
            self.flush()

    def _metadata(self) -> Dict[str, Any]:
        """Build ``metadata.yaml`` from the counters (caller holds ``_lock``)."""
        start_ns = self._start_ns or 0
        duration_ns = (self._end_ns - self._start_ns) if self._start_ns is not None else 0
        topics = [{
            'topic_metadata': {
                'name': t.name, 'type': t.type_name,
                'serialization_format': MESSAGE_ENCODING,
                'offered_qos_profiles': [dict(p) for p in t.offered_qos_profiles],
                'type_description_hash': t.type_description_hash,
            },
            'message_count': t.message_count,
        } for t in self._topics.values()]
        return {'rosbag2_bagfile_information': {
            'version': METADATA_VERSION,
            'storage_identifier': STORAGE_IDENTIFIER,
            'duration': {'nanoseconds': duration_ns},
            'starting_time': {'nanoseconds_since_epoch': start_ns},
            'message_count': self._message_count,
            'topics_with_message_count': topics,
            'compression_format': '' if self._compression == 'none' else self._compression,
            'compression_mode': '',
            'relative_file_paths': [self.file_name],
            'files': [{
                'path': self.file_name,
                'starting_time': {'nanoseconds_since_epoch': start_ns},
                'duration': {'nanoseconds': duration_ns},
                'message_count': self._message_count,
            }],
            'custom_data': dict(self._custom_data) if self._custom_data else None,
            'ros_distro': ROS_DISTRO,
        }}

    def _write_metadata(self) -> None:
        with self._lock:
            metadata = self._metadata()
        text = yaml.safe_dump(metadata, sort_keys=False, default_flow_style=False)
        with self._metadata_lock:
            # Write then rename: a kill mid-write never leaves a half metadata.yaml.
            temporary = self.folder / (METADATA_FILE + '.tmp')
            temporary.write_text(text, encoding='utf-8')
            os.replace(temporary, self.folder / METADATA_FILE)


class _BoundedStream:
    """The first ``limit`` bytes of a binary file, as a readable stream."""

    def __init__(self, stream, limit: int) -> None:
        self._stream = stream
        self._remaining = limit

    def read(self, size: int = -1) -> bytes:
        if size is None or size < 0 or size > self._remaining:
            size = self._remaining
        data = self._stream.read(size)
        self._remaining -= len(data)
        return data


def _complete_prefix(stream, file_size: int) -> int:
    """
    Return the length of the file up to its last complete top-level record.

    Records are ``opcode (1 byte), length (8 bytes), body``; a writer killed mid-write
    leaves the last one short.
    """
    stream.seek(0)
    if stream.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
        raise BagError(f'{getattr(stream, "name", "file")} is not an MCAP file')
    offset = len(_MCAP_MAGIC)
    while offset + _RECORD_HEADER.size <= file_size:
        stream.seek(offset)
        opcode, length = _RECORD_HEADER.unpack(stream.read(_RECORD_HEADER.size))
        end = offset + _RECORD_HEADER.size + length
        if end > file_size:
            break
        offset = end
        if opcode == Opcode.FOOTER:
            break
    return offset


class _McapFile:
    """One MCAP file of a bag: its schemas, channels and counts, read once at open."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.schemas: Dict[int, Schema] = {}
        self.channels: Dict[int, Channel] = {}
        self.counts: Dict[int, int] = {}
        self.start_ns: Optional[int] = None
        self.end_ns: Optional[int] = None
        self.complete = False
        self._counting = True
        try:
            with open(path, 'rb') as stream:
                summary = self._summary(stream)
                if summary is not None:
                    self.complete = True
                    self.schemas = dict(summary.schemas)
                    self.channels = dict(summary.channels)
                    statistics = summary.statistics
                    if statistics is not None:
                        self.counts = dict(statistics.channel_message_counts)
                        if statistics.message_count:
                            self.start_ns = statistics.message_start_time
                            self.end_ns = statistics.message_end_time
                        self._counting = False
                        return
                # No usable summary or statistics: scan the records once for the facts.
                for _ in self._stream_messages(stream):
                    pass
                self._counting = False
        except OSError as error:
            raise BagError(f'cannot read {path}: {error}') from error

    @staticmethod
    def _summary(stream):
        """Return the file's summary, or None when it has none (a crashed writer)."""
        size = stream.seek(0, os.SEEK_END)
        if size < 2 * len(_MCAP_MAGIC):
            return None
        stream.seek(size - len(_MCAP_MAGIC))
        if stream.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
            return None
        stream.seek(0)
        try:
            return make_reader(stream).get_summary()
        except (McapError, struct.error, ValueError):
            return None

    def _stream_messages(self, stream) -> Iterator[Tuple[Channel, Message]]:
        """Yield the messages of the complete records, filling schemas and channels."""
        size = stream.seek(0, os.SEEK_END)
        end = _complete_prefix(stream, size)
        stream.seek(0)
        reader = StreamReader(_BoundedStream(stream, end), skip_magic=False)
        records = reader.records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except McapError:
                # EndOfFile at the end of the complete prefix: the rest was cut off.
                return
            if isinstance(record, Schema):
                self.schemas[record.id] = record
            elif isinstance(record, Channel):
                self.channels[record.id] = record
            elif isinstance(record, Message):
                channel = self.channels.get(record.channel_id)
                if channel is None:
                    continue
                if self._counting:
                    self.counts[record.channel_id] = self.counts.get(record.channel_id, 0) + 1
                    if self.start_ns is None or record.log_time < self.start_ns:
                        self.start_ns = record.log_time
                    if self.end_ns is None or record.log_time > self.end_ns:
                        self.end_ns = record.log_time
                yield channel, record

    def messages(self, topics: Optional[Iterable[str]]) -> Iterator[Tuple[Channel, Message]]:
        """Yield (channel, message) in log-time order (file order among equal times)."""
        wanted = None if topics is None else set(topics)
        with open(self.path, 'rb') as stream:
            if self.complete:
                reader = make_reader(stream)
                for _, channel, message in reader.iter_messages(
                        topics=None if wanted is None else sorted(wanted),
                        log_time_order=True):
                    yield channel, message
                return
            # No index to merge by: sort the readable messages in memory.
            selected = [(channel, message) for channel, message in self._stream_messages(stream)
                        if wanted is None or channel.topic in wanted]
        selected.sort(key=lambda pair: pair[1].log_time)
        yield from selected


class BagReader:
    """
    Read a bag folder (or one ``.mcap`` file), also one whose writer was killed.

    A file without summary (the writer did not close it) is read record by record up to
    the last complete one; :attr:`complete` tells which case it is.
    """

    def __init__(self, path) -> None:
        """
        Open the bag and read its topics and counts.

        :param path: a bag folder (with or without ``metadata.yaml``) or an ``.mcap`` file.
        :raises BagError: no such bag, or not MCAP.
        """
        self.path = Path(path)
        if self.path.is_dir():
            files = self._files_of_folder(self.path)
        elif self.path.is_file():
            files = [self.path]
        else:
            raise BagError(f'no bag at {self.path}')
        self._files = [_McapFile(f) for f in files]
        self._decoders: Dict[Tuple[int, int], Any] = {}
        self._decoder_factory = DecoderFactory()

    @staticmethod
    def _files_of_folder(folder: Path) -> List[Path]:
        metadata_path = folder / METADATA_FILE
        files: List[Path] = []
        if metadata_path.is_file():
            try:
                info = yaml.safe_load(metadata_path.read_text(encoding='utf-8'))
                relative = info['rosbag2_bagfile_information']['relative_file_paths']
                files = [folder / name for name in relative if (folder / name).is_file()]
            except (OSError, yaml.YAMLError, KeyError, TypeError):
                files = []
        if not files:
            files = sorted(folder.glob('*.mcap'))
        if not files:
            raise BagError(f'bag folder {folder} holds no .mcap file')
        return files

    @property
    def complete(self) -> bool:
        """Whether every file was closed properly (has its summary)."""
        return all(f.complete for f in self._files)

    def topics(self) -> Dict[str, str]:
        """Return topic -> message type name, for every topic in the bag."""
        result = {}
        for mcap_file in self._files:
            for channel in mcap_file.channels.values():
                schema = mcap_file.schemas.get(channel.schema_id)
                result[channel.topic] = schema.name if schema is not None else ''
        return result

    def offered_qos_profiles(self, topic: str) -> List[Dict[str, Any]]:
        """Return the publishers' QoS profiles recorded for a topic (may be empty)."""
        for mcap_file in self._files:
            for channel in mcap_file.channels.values():
                if channel.topic == topic:
                    text = channel.metadata.get('offered_qos_profiles', '')
                    try:
                        profiles = yaml.safe_load(text) if text else []
                    except yaml.YAMLError as error:
                        raise BagError(f'{mcap_file.path}: bad offered_qos_profiles of '
                                       f'{topic}: {error}') from error
                    return list(profiles or [])
        raise BagError(f'topic {topic} is not in bag {self.path}')

    def definition(self, topic: str) -> str:
        """Return the schema text of a topic's type."""
        for mcap_file in self._files:
            for channel in mcap_file.channels.values():
                if channel.topic == topic:
                    schema = mcap_file.schemas.get(channel.schema_id)
                    return schema.data.decode('utf-8') if schema is not None else ''
        raise BagError(f'topic {topic} is not in bag {self.path}')

    def type_description_hash(self, topic: str) -> str:
        """Return the ``RIHS01_...`` hash recorded for a topic's type ('' if none)."""
        for mcap_file in self._files:
            for channel in mcap_file.channels.values():
                if channel.topic == topic:
                    return channel.metadata.get('topic_type_hash', '')
        raise BagError(f'topic {topic} is not in bag {self.path}')

    def message_counts(self) -> Dict[str, int]:
        """Return topic -> number of messages."""
        counts: Dict[str, int] = {}
        for mcap_file in self._files:
            for channel_id, channel in mcap_file.channels.items():
                counts[channel.topic] = (counts.get(channel.topic, 0)
                                         + mcap_file.counts.get(channel_id, 0))
        return counts

    @property
    def message_count(self) -> int:
        """Count the messages in the bag."""
        return sum(self.message_counts().values())

    @property
    def start_time_ns(self) -> Optional[int]:
        """Log time of the first message (ns since the epoch), None if empty."""
        times = [f.start_ns for f in self._files if f.start_ns is not None]
        return min(times) if times else None

    @property
    def end_time_ns(self) -> Optional[int]:
        """Log time of the last message (ns since the epoch), None if empty."""
        times = [f.end_ns for f in self._files if f.end_ns is not None]
        return max(times) if times else None

    def _raw(self, topics: Optional[Iterable[str]]):
        topics = None if topics is None else list(topics)
        streams = []
        for index, mcap_file in enumerate(self._files):
            streams.append(((message.log_time, index, mcap_file, channel, message)
                            for channel, message in mcap_file.messages(topics)))
        return heapq.merge(*streams, key=lambda item: (item[0], item[1]))

    def messages(self, topics: Optional[Iterable[str]] = None) -> Iterator[BagMessage]:
        """
        Yield the messages in log-time order.

        :param topics: only these topics; default all.
        """
        for _, _, mcap_file, channel, message in self._raw(topics):
            schema = mcap_file.schemas.get(channel.schema_id)
            yield BagMessage(channel.topic, schema.name if schema is not None else '',
                             message.log_time, message.publish_time, message.data)

    def decoded(self, topics: Optional[Iterable[str]] = None
                ) -> Iterator[Tuple[BagMessage, Any]]:
        """
        Yield ``(message, decoded)`` in log-time order, decoded by mcap_ros2's CDR decoder.

        The decoded object has the message's fields as attributes (not an rclpy class).

        :raises BagError: a topic whose schema cannot be decoded.
        """
        for _, index, mcap_file, channel, message in self._raw(topics):
            schema = mcap_file.schemas.get(channel.schema_id)
            key = (index, channel.schema_id)
            decoder = self._decoders.get(key)
            if decoder is None:
                decoder = self._decoder_factory.decoder_for(channel.message_encoding, schema)
                if decoder is None:
                    raise BagError(f'no decoder for {channel.topic} '
                                   f'({channel.message_encoding})')
                self._decoders[key] = decoder
            yield (BagMessage(channel.topic, schema.name, message.log_time,
                              message.publish_time, message.data),
                   decoder(message.data))


def recover(folder, output=None) -> Path:
    """
    Rewrite a bag whose writer was killed as a complete bag, with every readable message.

    :param folder: the crashed bag folder.
    :param output: folder for the complete bag; default: replace the crashed file (and
        ``metadata.yaml``) in ``folder`` itself.
    :returns: the folder of the complete bag.
    :raises BagError: ``folder`` is not a bag, or ``output`` is not empty.
    """
    folder = Path(folder)
    reader = BagReader(folder)
    in_place = output is None
    if in_place:
        if reader.complete and (folder / METADATA_FILE).is_file():
            return folder
        if len(reader._files) != 1:
            raise BagError(f'{folder}: in-place recovery handles one .mcap file; '
                           'give an output folder')
        original = reader._files[0].path
        target = folder.parent / f'.{folder.name}.recovering'
        if target.exists():
            shutil.rmtree(target)
        writer = BagWriter(target, flush_period_s=0.0, file_name=original.name)
    else:
        target = Path(output)
        writer = BagWriter(target, flush_period_s=0.0)
    with writer:
        for topic, type_name in reader.topics().items():
            writer.add_topic(topic, type_name, reader.offered_qos_profiles(topic),
                             definition=reader.definition(topic),
                             type_description_hash=reader.type_description_hash(topic))
        for message in reader.messages():
            writer.write(message.topic, message.data, message.log_time_ns,
                         message.publish_time_ns)
    if not in_place:
        return target
    os.replace(target / original.name, original)
    os.replace(target / METADATA_FILE, folder / METADATA_FILE)
    shutil.rmtree(target)
    return folder
