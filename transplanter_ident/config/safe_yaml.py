"""Bounded, safe loading of parameter files (DESIGN.md section 6; issue #14, bad input offline).

PyYAML's SafeLoader builds nothing but plain data, yet a small document can still stand for an
enormous one: aliases of aliases (a "billion laughs" bomb) share nodes while parsing, and the
expansion happens in whoever walks the result (flattening one such params file took 4.5 GB).
:func:`load_yaml_text` therefore composes the document first, counts it with the aliases expanded
(each node once, memoised; a recursive alias is refused) and refuses it before it is constructed
when it exceeds the limits below. :func:`read_text_file` reads at most ``MAX_BYTES`` and decodes
UTF-8. Every refusal is a :class:`YamlLimitError` whose one-line message names the reason; callers
prefix the file. :func:`check_sealed` refuses a sealed file (one :mod:`.params_writer` wrote) that
was cut short.

The loader also reads YAML 1.2 floats such as ``1e-4`` as numbers, as the rcl parser does.
This module imports no ROS.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

#: the largest parameter file read (bytes); a real one is a few kB
MAX_BYTES = 1 << 20
#: alias references (``*name``) in one document
MAX_ALIASES = 1000
#: scalars, sequences and mappings of one document once every alias is expanded
MAX_NODES = 100_000
#: levels of nesting
MAX_DEPTH = 64
#: the first and last lines of every file :mod:`.params_writer` writes (the tuner's output): a file that
#: starts with the first line but lacks the last one was cut short (a full disk, an interrupted copy)
SEALED_FIRST_LINE = "# transplanter_ident parameters; this file is complete only if it holds the line '# end'"
SEALED_LAST_LINE = "# end"


class YamlLimitError(ValueError):
    """A document that cannot be read, or exceeds the limits; the message is one line."""


class Loader(yaml.SafeLoader):
    """SafeLoader that reads YAML 1.2 floats such as ``1e-4`` as numbers and counts alias references."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.aliases = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_ALIASES:
                raise YamlLimitError(f"more than {MAX_ALIASES} aliases (*name): refused")
        return super().compose_node(parent, index)


Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def read_text_file(path: str | Path) -> str:
    """The UTF-8 text of ``path``, at most MAX_BYTES; OSError as raised, the rest as YamlLimitError."""
    with open(path, "rb") as handle:  # noqa: PTH123 - a FIFO or /dev/zero is read only this far
        data = handle.read(MAX_BYTES + 1)
    if len(data) > MAX_BYTES:
        raise YamlLimitError(f"larger than {MAX_BYTES // 1024} kB: not a parameters file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise YamlLimitError(f"not UTF-8 text (byte 0x{data[exc.start]:02x} on line {line})") from None


def load_yaml_text(text: str) -> Any:
    """Parse one YAML document within the limits; YamlLimitError (with the line where known) otherwise."""
    try:
        loader = Loader(text)  # the reader refuses control characters here already
        try:
            node = loader.get_single_node()
            if node is None:
                return None
            expanded_size(node)
            return loader.construct_document(node)
        finally:
            loader.dispose()
    except YamlLimitError:
        raise
    except yaml.YAMLError as exc:
        raise YamlLimitError(_describe(exc)) from None
    except RecursionError:
        raise YamlLimitError("nested too deeply") from None


def check_sealed(text: str) -> None:
    """A text that starts with SEALED_FIRST_LINE must also hold SEALED_LAST_LINE, else YamlLimitError.

    A user may edit a sealed file (even append to it); only a file cut before its last line is refused.
    """
    lines = [line.strip() for line in text.splitlines()]
    if lines and lines[0] == SEALED_FIRST_LINE and SEALED_LAST_LINE not in lines[1:]:
        raise YamlLimitError(f"incomplete: written by transplanter_ident (its first line says so) but its closing "
                             f"line '{SEALED_LAST_LINE}' is missing, so it was cut short (full disk? interrupted "
                             "copy?) and a value may have been cut too: write it again (re-run the tuner), or delete "
                             "the first line to use it as it is")


def short_repr(value: Any, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters (values in messages stay one short line)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 5] + " ...]"


def _describe(exc: yaml.YAMLError) -> str:
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    if isinstance(exc, yaml.reader.ReaderError):  # a control character: its position, not its Python repr
        return f"invalid YAML: character #x{exc.character:04x} at position {exc.position} is not allowed"
    reason = getattr(exc, "problem", None) or type(exc).__name__
    return f"invalid YAML{where}: {' '.join(str(reason).split())}"


def expanded_size(root: yaml.Node) -> int:
    """Nodes of the document with every alias expanded; YamlLimitError beyond MAX_NODES or MAX_DEPTH.

    Iterative, and each node is sized once (shared nodes come from aliases), so a bomb costs
    no more than its text.
    """
    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, int, bool]] = [(root, 1, False)]
    while stack:
        node, depth, children_done = stack.pop()
        key = id(node)
        if key in sizes:
            continue
        children = _children(node)
        if not children_done:
            if key in on_path:
                raise YamlLimitError("an alias refers to a node that contains it (recursive document)")
            if depth > MAX_DEPTH:
                raise YamlLimitError(f"nested more than {MAX_DEPTH} levels deep")
            on_path.add(key)
            stack.append((node, depth, True))
            stack.extend((child, depth + 1, False) for child in children if id(child) not in sizes)
            continue
        on_path.discard(key)
        total = 1 + sum(sizes[id(child)] for child in children)
        if total > MAX_NODES:
            raise YamlLimitError(f"more than {MAX_NODES} values once its aliases are expanded: refused")
        sizes[key] = total
    return sizes[id(root)]


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [part for pair in node.value for part in pair]
    return []
