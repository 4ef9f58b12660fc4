"""One hardened loader for every file from outside: missions, camera calibrations, rig files.

`load_yaml(path)` returns the document and a map from key paths to line numbers, or raises LoadError with
one line naming the file and, where there is one, the line and the key path. Before anything is parsed:

- the path must be a regular file: directories, devices (/dev/zero: read until memory ran out), FIFOs
  (the open hung) and sockets are refused; the file is opened with O_NONBLOCK so that not even a FIFO
  can block the open, then checked with fstat;
- at most MAX_BYTES (1 MiB) are read; a larger file is refused;
- the text must be UTF-8 (a UTF-8 byte-order mark is skipped); UTF-16/32 files and invalid bytes are
  refused naming the byte offset.

YAML is parsed with libyaml's C parser when PyYAML has it (CSafeLoader), else the pure-Python SafeLoader,
composed into nodes, and the node tree is checked *before* any Python object is built:

- anchors and aliases are refused (a 1.8 KB alias bomb once expanded to 184 MB): an alias shows as a
  node that is reached twice;
- at most MAX_DEPTH (64) nested collections and MAX_NODES (200,000) nodes;
- duplicate mapping keys are refused (PyYAML silently keeps the last);
- integers of more than MAX_INT_DIGITS (30) digits are refused (Python refuses to convert more than
  4,300 digits, deep inside the constructor);
- a RecursionError or MemoryError from the parser is turned into a LoadError; text that might nest
  deeper than C_SAFE_DEPTH is never given to libyaml's composer, which crashes the process instead.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import yaml

MAX_BYTES = 1 << 20
MAX_DEPTH = 64
MAX_NODES = 200_000
MAX_INT_DIGITS = 30
C_SAFE_DEPTH = 1000  # depth_bound beyond which the C composer is not used (it crashes near 1e5)
_INT_TAG = "tag:yaml.org,2002:int"
_Loader: type = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
Lines = dict[tuple[str, ...], int]  # key path → 1-based line


class LoadError(ValueError):
    """A file that cannot be loaded; the message is one line naming the file and why."""


def read_text(path: str | Path, what: str = "file", max_bytes: int = MAX_BYTES) -> str:
    """The UTF-8 text of the regular file `path` (at most max_bytes bytes); LoadError otherwise."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except OSError as exc:
        raise LoadError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = (
                "a directory"
                if stat.S_ISDIR(mode)
                else "a FIFO"
                if stat.S_ISFIFO(mode)
                else "a device"
                if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
                else "a socket"
                if stat.S_ISSOCK(mode)
                else "not a regular file"
            )
            raise LoadError(f"{path}: the {what} is {kind}, not a regular file")
        chunks: list[bytes] = []
        size = 0
        while size <= max_bytes:
            chunk = os.read(fd, min(1 << 16, max_bytes + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise LoadError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    data = b"".join(chunks)
    if len(data) > max_bytes:
        raise LoadError(f"{path}: the {what} is larger than {max_bytes} bytes")
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise LoadError(f"{path}: the {what} is UTF-16 text; save it as UTF-8")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise LoadError(f"{path}: the {what} is not UTF-8 text (byte {exc.start})") from None


def _where(node: yaml.Node, path: tuple[str, ...]) -> str:
    key = ".".join(path)
    if len(key) > 80:
        key = key[:38] + "..." + key[-38:]
    return f"line {node.start_mark.line + 1}" + (f", {key}" if key else "")


def _check_tree(root: yaml.Node, source: str) -> Lines:
    """Refuse aliases, deep nesting, too many nodes, duplicate keys and huge integers; key path → line."""
    seen: set[int] = set()
    lines: Lines = {}
    stack: list[tuple[yaml.Node, tuple[str, ...], int]] = [(root, (), 0)]
    while stack:
        node, path, depth = stack.pop()
        if id(node) in seen:
            raise LoadError(f"{source}: {_where(node, path)}: anchors and aliases are not allowed")
        seen.add(id(node))
        if len(seen) > MAX_NODES:
            raise LoadError(f"{source}: more than {MAX_NODES} values")
        if depth > MAX_DEPTH:
            raise LoadError(f"{source}: {_where(node, path)}: nested deeper than {MAX_DEPTH} levels")
        lines.setdefault(path, node.start_mark.line + 1)
        if isinstance(node, yaml.ScalarNode):
            digits = sum(c.isdigit() for c in node.value)
            if node.tag == _INT_TAG and digits > MAX_INT_DIGITS:
                raise LoadError(f"{source}: {_where(node, path)}: an integer of {digits} digits")
        elif isinstance(node, yaml.SequenceNode):
            stack.extend((item, (*path, str(i)), depth + 1) for i, item in enumerate(node.value))
        elif isinstance(node, yaml.MappingNode):
            keys: set[str] = set()
            for k, v in node.value:
                name = str(k.value) if isinstance(k, yaml.ScalarNode) else "<complex key>"
                if name in keys:
                    raise LoadError(f"{source}: {_where(k, path)}: duplicate key {name!r}")
                keys.add(name)
                stack.append((k, (*path, name, "<key>"), depth + 1))
                stack.append((v, (*path, name), depth + 1))
    return lines


def depth_bound(text: str) -> int:
    """An upper bound on the nesting depth of the YAML `text`, without parsing: the deepest running count
    of [ and { (brackets in strings and comments only raise it) plus the widest line's indentation and
    block indicators ("- ", "? ", ": "); block nesting needs either more indentation or an indicator."""
    flow = depth = 0
    for ch in text:
        if ch in "[{":
            flow += 1
            depth = max(depth, flow)
        elif ch in "]}":
            flow = max(0, flow - 1)
    block = 0
    for line in text.splitlines():
        indent = len(line) - len(line.lstrip(" "))
        block = max(block, indent + line.count("- ") + line.count("? ") + line.count(": "))
    return depth + block


def parse_yaml(text: str, source: str) -> tuple[Any, Lines]:
    """The document in `text` and its key path → line map; LoadError (naming `source`) otherwise.

    libyaml's C composer recurses in C on nesting and crashes the process (segmentation fault) past some
    100,000 levels; text whose depth_bound exceeds C_SAFE_DEPTH is therefore composed by PyYAML's Python
    loader, whose recursion ends in a RecursionError (refused like any other bad input)."""
    loader = (_Loader if depth_bound(text) <= C_SAFE_DEPTH else yaml.SafeLoader)(text)
    try:
        try:
            root = loader.get_single_node()
        except yaml.MarkedYAMLError as exc:
            mark = exc.problem_mark
            at = f"line {mark.line + 1}: " if mark is not None else ""
            raise LoadError(f"{source}: {at}not valid YAML ({exc.problem or exc})") from None
        except yaml.YAMLError as exc:
            raise LoadError(f"{source}: not valid YAML ({exc})") from None
        if root is None:
            return None, {}
        lines = _check_tree(root, source)
        try:
            return loader.construct_document(root), lines
        except yaml.YAMLError as exc:
            raise LoadError(f"{source}: cannot read a value ({str(exc).splitlines()[0]})") from None
        except ValueError as exc:  # e.g. an out-of-range timestamp
            raise LoadError(f"{source}: cannot read a value ({exc})") from None
    except (RecursionError, MemoryError):
        raise LoadError(f"{source}: nested too deeply or too large to read") from None
    finally:
        loader.dispose()


def load_yaml(path: str | Path, what: str = "file") -> tuple[Any, Lines]:
    """Read (read_text) and parse (parse_yaml) the YAML file `path`."""
    return parse_yaml(read_text(path, what), str(path))


def line_of(lines: Lines, loc: tuple[object, ...]) -> int | None:
    """The line of the deepest key path of `loc` (a pydantic error location) that the file has."""
    path = tuple(str(p) for p in loc)
    while path:
        if path in lines:
            return lines[path]
        path = path[:-1]
    return None


__all__ = ["MAX_BYTES", "MAX_DEPTH", "LoadError", "line_of", "load_yaml", "parse_yaml", "read_text"]
