"""Dataclass configs as command lines (CleanRL style), TOML config files and output guards.

A training script's knobs are one dataclass whose fields are declared with :func:`arg`
(default and meaning, stored in the field's metadata so that ``--help`` never depends on
reading the source); a subclass may override a default with a plain value and keeps the
inherited meaning. :func:`parse_config` turns it into the command line:

* every field is a ``--kebab-case`` option (``bool``: ``--flag / --no-flag``) whose ``--help``
  line gives its meaning and its default;
* ``--config FILE`` reads a TOML file of field values (keys: the field names), which replace
  the dataclass defaults; options given on the command line override the file. Unknown keys,
  values of the wrong type and a ``script`` key naming another script exit with code 2 and
  one line naming the key and the file. Two keys are not applied: ``script`` (the module the
  file is for, checked) and ``out`` (the checkpoint the file reproduces: outputs always go
  where ``--out`` says, under ``runs/`` by default); ``force`` is refused in a file (pass it on
  the command line);
* usage errors are one line on stderr and exit code 2.

:func:`check_outputs` is what every script calls before any work: an existing output file
without ``--force``, or an output folder where a real test write fails (full disk, read-only,
no permission), is exit code 2 with one line naming the file or folder and the cause.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from selenv.atomic import describe_os_error, probe_replaceable, probe_writable
from selenv.untrusted import UntrustedInputError, read_toml_file

__all__ = [
    "FILE_ONLY_KEYS",
    "NOT_IN_FILES",
    "ConfigFileError",
    "UsageParser",
    "arg",
    "build_parser",
    "check_outputs",
    "field_help",
    "option_name",
    "parse_config",
    "read_config_file",
    "usage_error",
]

C = TypeVar("C")
T = TypeVar("T")

#: keys a config file may hold that are not applied as values (see the module docstring)
FILE_ONLY_KEYS = ("script", "out")
#: fields that only the command line may set
NOT_IN_FILES = ("force",)
_TYPES: dict[str, type] = {"int": int, "float": float, "str": str, "bool": bool}
_TOML_NAMES = {bool: "boolean", int: "integer", float: "float", str: "string", dict: "table",
               list: "array"}  # fmt: skip


class ConfigFileError(ValueError):
    """A config file that cannot be applied (missing, not TOML, unknown key, wrong type)."""


def arg(default: T, help: str, *, choices: Sequence[Any] | None = None) -> T:
    """A config field: its ``default`` and its meaning ``help`` (shown by ``--help``).

    ``choices``: the allowed values (checked on the command line and in config files).
    """
    metadata: dict[str, Any] = {"help": help}
    if choices is not None:
        metadata["choices"] = tuple(choices)
    return dataclasses.field(default=default, metadata=metadata)


def _meta(cls: type, name: str, key: str) -> Any:
    """``key`` of field ``name``'s metadata in the nearest class of ``cls``'s MRO that has it."""
    for klass in cls.__mro__:
        f = getattr(klass, "__dataclass_fields__", {}).get(name)
        if f is not None and key in f.metadata:
            return f.metadata[key]
    return None


def field_help(cls: type) -> dict[str, str]:
    """Field name -> its meaning (the nearest :func:`arg` declaration along the MRO).

    Raises:
        TypeError: ``cls`` is not a dataclass, or a field has no (or an empty) meaning.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"cls must be a dataclass, got {cls!r}")
    out = {}
    for f in dataclasses.fields(cls):
        text = _meta(cls, f.name, "help")
        if not isinstance(text, str) or not text.strip():
            raise TypeError(
                f"{cls.__qualname__}.{f.name} has no description: declare it with "
                f"selenv.learned.config.arg(default, help)"
            )
        out[f.name] = text.strip()
    return out


def option_name(name: str) -> str:
    """The command-line option of field ``name`` (``lambda_`` -> ``--lambda``)."""
    return "--" + name.rstrip("_").replace("_", "-")


def _base_type(f: dataclasses.Field[Any]) -> tuple[type, bool]:
    """(int / float / str / bool, whether ``None`` is allowed) of a field's annotation."""
    text = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    parts = [p.strip() for p in str(text).split("|")]
    optional = "None" in parts
    parts = [p for p in parts if p != "None"]
    if len(parts) != 1 or parts[0] not in _TYPES:
        raise TypeError(f"field {f.name}: unsupported type {text!r} (int, float, str, bool)")
    return _TYPES[parts[0]], optional


def _shown(value: Any) -> str:
    if value == "":
        return '""'
    return str(value)


class UsageParser(argparse.ArgumentParser):
    """``argparse`` whose usage errors are one line on stderr, exit code 2."""

    def error(self, message: str) -> NoReturn:
        """Print ``PROG: error: message`` on one line and exit 2."""
        usage_error(self.prog, message)


class _Flag(argparse.BooleanOptionalAction):
    """``--flag / --no-flag`` whose help is exactly what it is given (defaults shown once)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        help_text = kwargs.get("help")
        super().__init__(*args, **kwargs)
        self.help = help_text


def usage_error(prog: str, message: object) -> NoReturn:
    """Print ``PROG: error: MESSAGE`` (one line) on stderr and exit with code 2."""
    text = " ".join(str(message).split())
    print(f"{prog}: error: {text}", file=sys.stderr)
    raise SystemExit(2)


def build_parser(
    cls: type,
    description: str,
    *,
    prog: str | None = None,
    defaults: Mapping[str, Any] | None = None,
) -> argparse.ArgumentParser:
    """The command line of dataclass ``cls`` (plus ``--config``), ``defaults`` overriding.

    Every option's help is its meaning followed by ``(default: X)``.
    """
    helps = field_help(cls)
    parser = UsageParser(prog=prog, description=description, allow_abbrev=False)
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="TOML file of option values, keys as the field names (total_timesteps = 1000): "
        "they replace the defaults, options given on the command line override them; the "
        "file's 'out' (the checkpoint it reproduces) is not applied (default: none)",
    )
    values = {f.name: f.default for f in dataclasses.fields(cls)}
    values.update(defaults or {})
    for f in dataclasses.fields(cls):
        typ, _ = _base_type(f)
        default = values[f.name]
        text = f"{helps[f.name]} (default: {_shown(default)})".replace("%", "%%")
        kwargs: dict[str, Any] = {"default": default, "help": text, "dest": f.name}
        choices = _meta(cls, f.name, "choices")
        if typ is bool:
            parser.add_argument(option_name(f.name), action=_Flag, **kwargs)
        else:
            if choices is not None:
                kwargs["choices"] = choices
            parser.add_argument(option_name(f.name), type=typ, **kwargs)
    return parser


def _toml_name(value: Any) -> str:
    return next((n for t, n in _TOML_NAMES.items() if isinstance(value, t)), type(value).__name__)


def _tomllib() -> Any:
    """``tomllib`` (Python >= 3.11) or its backport ``tomli`` (Python 3.10)."""
    for name in ("tomllib", "tomli"):
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError:  # pragma: no cover - Python 3.10
            continue
    raise ConfigFileError("--config needs Python >= 3.11 or the tomli package (pip install tomli)")


def read_config_file(
    path: str | Path, cls: type, *, script: str | None = None
) -> tuple[dict[str, Any], dict[str, str]]:
    """Field values of the TOML file ``path`` for ``cls``, and its ``script`` / ``out`` keys.

    Raises:
        ConfigFileError: the file is missing, not TOML, larger or nested deeper than
            :data:`selenv.untrusted.LIMITS` allows (checked before parsing); a key is not a
            field of ``cls`` (or is ``force``); a value has the wrong type or is not among the
            field's choices; ``script`` is given and names another module than ``script``.
    """
    _tomllib()
    try:  # bounded: size and nesting are checked before (and after) parsing
        data = read_toml_file(path, "--config")
    except FileNotFoundError:
        raise ConfigFileError(f"--config {path}: cannot read it (no such file)") from None
    except UntrustedInputError as exc:
        raise ConfigFileError(str(exc)) from None
    fields = {f.name: f for f in dataclasses.fields(cls)}
    values: dict[str, Any] = {}
    info: dict[str, str] = {}
    for key, value in data.items():
        if key in FILE_ONLY_KEYS:
            if not isinstance(value, str):
                raise ConfigFileError(
                    f"{path}: key '{key}' must be a string, got {_toml_name(value)} {value!r}"
                )
            info[key] = value
            continue
        if key in NOT_IN_FILES:
            raise ConfigFileError(
                f"{path}: key '{key}' is not allowed in a config file (pass --{key} on the "
                "command line)"
            )
        if key not in fields:
            valid = [*FILE_ONLY_KEYS, *(k for k in fields if k not in NOT_IN_FILES)]
            raise ConfigFileError(f"{path}: unknown key '{key}' (valid keys: {', '.join(valid)})")
        typ, _ = _base_type(fields[key])
        ok = isinstance(value, typ) and (typ is bool or not isinstance(value, bool))
        if typ is float and isinstance(value, int) and not isinstance(value, bool):
            value, ok = float(value), True
        if not ok:
            raise ConfigFileError(
                f"{path}: key '{key}' must be a TOML {_TOML_NAMES[typ]}, got "
                f"{_toml_name(value)} {value!r}"
            )
        choices = _meta(cls, key, "choices")
        if choices is not None and value not in choices:
            raise ConfigFileError(
                f"{path}: key '{key}' must be one of {', '.join(map(str, choices))}, got {value!r}"
            )
        values[key] = value
    if script is not None and info.get("script", script) != script:
        raise ConfigFileError(
            f"{path}: key 'script' is {info['script']!r}: the file is for that script, not {script}"
        )
    return values, info


def parse_config(
    cls: type[C], argv: list[str] | None, description: str, *, script: str | None = None
) -> C:
    """Build a ``cls`` instance (a dataclass of :func:`arg` fields) from ``argv``.

    ``argv=None`` reads ``sys.argv``. ``script`` (``"selenv.train.train_fim_ppo"``) names the
    program in messages and is the ``script`` a config file must name if it names one.
    Usage and config-file errors exit with code 2 (one line on stderr).
    """
    args = sys.argv[1:] if argv is None else list(argv)
    prog = f"python -m {script}" if script else None
    pre = UsageParser(prog=prog, add_help=False, allow_abbrev=False)
    pre.add_argument("--config")
    known, _ = pre.parse_known_args(args)
    defaults: dict[str, Any] = {}
    info: dict[str, str] = {}
    if known.config is not None:
        try:
            defaults, info = read_config_file(known.config, cls, script=script)
        except ConfigFileError as exc:
            usage_error(pre.prog, exc)
    parser = build_parser(cls, description, prog=prog, defaults=defaults)
    ns = vars(parser.parse_args(args))
    ns.pop("config")
    if "out" in info and "out" in ns and ns["out"] == parser.get_default("out"):
        print(
            f"{parser.prog}: note: {known.config} describes {info['out']}, which is not "
            f"replaced: this run writes its default --out (pass --out {info['out']} --force "
            "to replace it)",
            file=sys.stderr,
        )
    return cls(**ns)


def _unwritable(folder: Path) -> str | None:
    """Why files cannot be created in ``folder`` (created if missing), or ``None``.

    A real write probe (:func:`selenv.atomic.probe_writable`: create, write 4 KB, ``fsync``,
    remove) in ``folder`` or, if it does not exist yet, in its nearest existing ancestor (no
    folder is created): ``os.access`` says yes to root on a full or read-only disk.
    """
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a folder"
    try:
        probe_writable(existing / "write-probe")
    except OSError as exc:
        return describe_os_error(exc, existing).removeprefix(f"cannot write {existing}: ")
    return None


def check_outputs(
    prog: str,
    files: Iterable[str | Path],
    *,
    force: bool,
    option: str = "--out",
    folders: Iterable[str | Path] = (),
) -> None:
    """Refuse, before any work, outputs that would overwrite files or cannot be written.

    Exit code 2 with one line on stderr when one of ``files`` exists and ``force`` is false
    (naming the files, ``--force`` and ``option``), is a folder, or when the folder of a
    file, or one of ``folders``, cannot be created or written: a real write probe, so a full
    disk (``ENOSPC``) or a read-only file system is found here, not after the run.
    """
    paths = [Path(p) for p in files]
    for path in paths:
        if path.is_dir():
            usage_error(prog, f"{option} {path}: is a folder, expected a file path")
    existing = [str(p) for p in paths if p.exists()]
    if existing and not force:
        verb = "exists" if len(existing) == 1 else "exist"
        usage_error(
            prog,
            f"{', '.join(existing)} {verb}: pass --force to overwrite, or choose another {option}",
        )
    for path in paths:
        try:  # --force onto an immutable or append-only file: found now, not after the run
            probe_replaceable(path)
        except OSError as exc:
            usage_error(prog, f"{option} {describe_os_error(exc).removeprefix('cannot write ')}")
    for folder in dict.fromkeys([*(p.parent for p in paths), *map(Path, folders)]):
        problem = _unwritable(folder)
        if problem is not None:
            usage_error(prog, f"cannot write into {folder}: {problem}")
