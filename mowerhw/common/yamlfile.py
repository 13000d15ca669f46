"""YAML the way mowerhw reads what people write by hand: the runtime config and the camera
calibration (docs/design.md §8). A safe loader with three refusals PyYAML does not make:

- aliases (``*name``): a "billion laughs" document expands from them;
- nesting deeper than :data:`MAX_YAML_DEPTH`;
- a key given twice in one mapping: PyYAML keeps the second silently, so a pasted
  ``stale_after_s`` under the first would change a safety limit with no word said.

Errors are :class:`yaml.YAMLError` with the line and column of the problem."""

from __future__ import annotations

from typing import Any

import yaml

#: a hand-written YAML document nests at most this deep
MAX_YAML_DEPTH = 16


class StrictLoader(yaml.SafeLoader):
    """A :class:`yaml.SafeLoader` without aliases, with a bounded nesting depth and with
    every mapping's keys unique."""

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, "aliases (*name) are not allowed here", event.start_mark
            )
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise yaml.composer.ComposerError(
                    None,
                    None,
                    f"nested more than {MAX_YAML_DEPTH} levels deep",
                    self.peek_event().start_mark,
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        first: dict[Any, int] = {}
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                continue  # a complex key: the safe constructor refuses it itself
            key = self.construct_object(key_node, deep=True)
            if key in first:
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"the key {key!r} is given twice (first on line {first[key] + 1}); "
                    "each key once",
                    key_node.start_mark,
                )
            first[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep)


def load_yaml(text: str) -> Any:
    """The one YAML document in ``text``, read by :class:`StrictLoader`."""
    return yaml.load(text, Loader=StrictLoader)  # a SafeLoader underneath
