"""YAML a user hands the stack (sweep specs, robot files), read within bounds and refused in one line.

``yaml.safe_load`` never runs code, but it lets a small file cost without bound: aliases are shared objects, so
2 KB of nested aliases (30 levels of 10) stand for 10^30 values that the first walk over the data expands (a
spec's checks ran past a minute); an alias inside its own anchor builds a cycle (RecursionError); a 5000-digit
integer raises a ValueError; ``"\\ud800"`` gives a lone surrogate that fails when it is printed or written. Here:

- :func:`read_text_file`: a regular file of at most ``max_bytes`` (lq_ros.core.bounded_file), UTF-8.
- :func:`load_yaml`: at most :data:`MAX_DEPTH` levels of nesting, no alias inside its own anchor, and the data
  with every alias expanded at most :data:`MAX_VALUES` values (counted on the node graph, without expanding it);
  integers of at most :data:`MAX_INT_DIGITS` digits; no lone surrogate in any string.

Every refusal is a :class:`YamlRefused` (a ValueError) with one line naming the file and the problem.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from lq_ros.core.bounded_file import FileRefused, read_regular_file

#: Most levels of nesting (mappings and lists inside each other) a document may have.
MAX_DEPTH = 64
#: Most values a document may stand for once its aliases are expanded (a sweep spec has a few hundred).
MAX_VALUES = 100_000
#: Most digits of an integer (2**63 has 19).
MAX_INT_DIGITS = 30


class YamlRefused(ValueError):
    """A YAML file or document the stack will not read: one line naming it and the problem."""


def read_text_file(path: Path | str, max_bytes: int, what: str = "file") -> str:
    """The UTF-8 text of ``path`` if it is a regular file of at most ``max_bytes`` (YamlRefused otherwise)."""
    try:
        data = read_regular_file(path, max_bytes, what)
    except FileRefused as exc:
        raise YamlRefused(str(exc)) from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise YamlRefused(f"{what} {path}: not a text file ({exc.reason} at byte {exc.start})") from None


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader whose composer refuses deep nesting and aliases inside their own anchor (pure Python: the
    C loader's composer cannot be watched)."""

    def __init__(self, stream) -> None:
        super().__init__(stream)
        self._depth = 0
        self._open_anchors: set[str] = set()

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            anchor = self.peek_event().anchor
            if anchor in self._open_anchors:
                mark = self.peek_event().start_mark
                raise YamlRefused(f"alias *{anchor} inside its own anchor (line {mark.line + 1}): a cycle")
            return super().compose_node(parent, index)
        self._depth += 1
        if self._depth > MAX_DEPTH:
            mark = self.peek_event().start_mark
            raise YamlRefused(f"nested more than {MAX_DEPTH} levels deep (line {mark.line + 1})")
        anchor = getattr(self.peek_event(), "anchor", None)
        if anchor is not None:
            self._open_anchors.add(anchor)
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1
            if anchor is not None:
                self._open_anchors.discard(anchor)

    def construct_yaml_int(self, node):
        digits = sum(c.isalnum() for c in str(node.value))  # decimal, hex, octal or binary digits (and the prefix)
        if digits > MAX_INT_DIGITS:
            line = node.start_mark.line + 1
            raise YamlRefused(f"an integer of {digits} digits (line {line}); at most {MAX_INT_DIGITS}")
        return super().construct_yaml_int(node)

    def construct_yaml_str(self, node):
        value = super().construct_yaml_str(node)
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise YamlRefused(
                f"text with a lone surrogate (line {node.start_mark.line + 1}): not a valid character"
            ) from None
        return value


_BoundedLoader.add_constructor("tag:yaml.org,2002:int", _BoundedLoader.construct_yaml_int)
_BoundedLoader.add_constructor("tag:yaml.org,2002:str", _BoundedLoader.construct_yaml_str)


def _expanded_values(node: yaml.Node, sizes: dict[int, int]) -> int:
    """How many values ``node`` stands for with every alias expanded (each distinct node counted once)."""
    key = id(node)
    if key in sizes:
        return sizes[key]
    if isinstance(node, yaml.MappingNode):
        total = 1 + sum(_expanded_values(k, sizes) + _expanded_values(v, sizes) for k, v in node.value)
    elif isinstance(node, yaml.SequenceNode):
        total = 1 + sum(_expanded_values(item, sizes) for item in node.value)
    else:
        total = 1
    sizes[key] = min(total, MAX_VALUES + 1)
    return sizes[key]


def load_yaml(text: str, where: str) -> object:
    """The document in ``text``, within the bounds above; YamlRefused naming ``where`` otherwise."""
    loader = _BoundedLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        values = _expanded_values(node, {})
        if values > MAX_VALUES:
            raise YamlRefused(f"aliases expand to more than {MAX_VALUES} values")
        return loader.construct_document(node)
    except YamlRefused as exc:
        raise YamlRefused(f"{where}: {exc}") from None
    except yaml.YAMLError as exc:
        raise YamlRefused(f"{where}: not valid YAML ({' '.join(str(exc).split())})") from None
    except (ValueError, RecursionError) as exc:  # a value the constructor cannot build (e.g. a bad timestamp)
        why = " ".join(str(exc).split())[:200]
        raise YamlRefused(f"{where}: not valid YAML ({type(exc).__name__}: {why})") from None
    finally:
        loader.dispose()
