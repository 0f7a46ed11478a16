"""Plain YAML documents built straight from libyaml's events: the fast path of
:func:`larc_jax.io.parse_yaml_documents`.

Why. A planned trajectory file is about 3,000 YAML values, nearly all numbers in flow lists.
PyYAML's composer and constructor build a node object per value and then a Python object per
node, in pure Python: about 12 ms a file here, 80 % of reading one, and most of a
20,000-row manifest's time (``experiments.bench``). libyaml's C composer (``CSafeLoader``) is
not the answer: it composes recursively without the depth check of
:func:`larc_jax.io.parse_yaml_documents` and still constructs in Python.

What. :func:`plain_documents` walks the parser's event stream once and builds the documents
without nodes. It accepts only *plain* streams: no anchor, no alias, no explicit tag (``!``,
the non-specific tag, is allowed, as the composer allows it), no merge key, only scalar keys,
no key twice in a mapping, at most ``max_nesting`` nested lists and mappings, at most
``max_values`` events. On anything else, or on any parse error, it returns ``None`` and the
caller runs the full loader, which then gives the same documents or the same error.

Why the result equals the full loader's (``SafeYamlLoader``: PyYAML's ``Composer``, a
``SafeConstructor`` that refuses duplicate keys, ``Resolver``, libyaml's ``CParser``):

* The events are the same ones: both read them from a ``CParser`` of the same text.
* Without anchors and aliases the composed graph is a tree whose nodes are the events'
  start/scalar events in order; sequences and mappings take the default tags, as
  ``Composer`` does through ``Resolver.resolve`` when the tag is ``None`` or ``!`` (no path
  resolvers are registered on the loader; :func:`plain_documents` falls back if any is).
* A scalar's tag is resolved by the same rule as ``BaseResolver.resolve``: when the event is
  implicit for plain scalars, the loader's own implicit resolvers for the first character
  (``''`` for an empty value) then the wildcard ones, in order, first match wins; else ``str``.
  The value is then built by the loader's own constructor for that tag, except in two cases
  written out here because they are most of a trajectory file: a float whose text has only
  the characters ``0-9 . + - e E`` is ``float(text)`` (``construct_yaml_float`` strips a sign,
  lower-cases, and multiplies ``float`` of the rest by the sign: the same double, ``-0.0``
  included, since negation is exact), and an int of ASCII digits with no leading zero is
  ``int(text)`` (``construct_yaml_int`` reads a leading ``0`` as octal, so those go to it).
* Lists and mappings are built as ``construct_yaml_seq`` and ``construct_yaml_map`` build them
  (a list of the items; a dict of key -> value in order), keys being constructed scalars;
  ``flatten_mapping`` changes nothing when no key resolves to the merge tag. A key that is
  already in the mapping is what the full loader refuses: fall back, and it does.
* Checks of :func:`larc_jax.io.parse_yaml_documents` on the result (``check_shape``): the
  depth is bounded here, a tree cannot contain itself, and its value count is at most the
  number of events, bounded here.
"""

from __future__ import annotations

import string

import yaml
from yaml.events import (
    DocumentEndEvent,
    DocumentStartEvent,
    MappingEndEvent,
    MappingStartEvent,
    ScalarEvent,
    SequenceEndEvent,
    SequenceStartEvent,
    StreamEndEvent,
    StreamStartEvent,
)

__all__ = ["plain_documents"]

STR_TAG = "tag:yaml.org,2002:str"
FLOAT_TAG = "tag:yaml.org,2002:float"
INT_TAG = "tag:yaml.org,2002:int"
MERGE_TAG = "tag:yaml.org,2002:merge"
FLOAT_CHARS = frozenset(string.digits + ".+-eE")
"""Texts of floats that ``float()`` reads as ``construct_yaml_float`` does (module doc)."""
NON_SPECIFIC = (None, "!")
"""Event tags that the composer resolves (every other tag is explicit: not plain)."""


class NotPlain(Exception):
    """The stream is outside what :func:`plain_documents` builds; the full loader reads it."""


def _resolvers(loader_cls) -> tuple[dict, list]:
    """First character -> the implicit resolvers tried, in ``BaseResolver.resolve``'s order."""
    table = loader_cls.yaml_implicit_resolvers
    wildcard = list(table.get(None, []))
    return {key: list(value) + wildcard for key, value in table.items() if key is not None}, wildcard


def plain_documents(text: str, loader_cls, max_nesting: int, max_values: int) -> list | None:
    """The documents of ``text`` as ``yaml.load_all(text, Loader=loader_cls)`` returns them, or
    ``None`` when the stream is not plain or does not parse (module doc: then the caller runs
    the full loader). Events come from ``loader_cls``'s own parser, constructors from its own
    table."""
    if loader_cls.yaml_path_resolvers:
        return None
    loader = loader_cls(text)
    try:
        return _build(loader, max_nesting, max_values)
    except (NotPlain, yaml.YAMLError, ValueError, OverflowError, RecursionError):
        return None
    finally:
        loader.dispose()


def _scalar(loader, event, by_char: dict, wildcard: list):
    if event.anchor is not None or event.tag not in NON_SPECIFIC:
        raise NotPlain
    value = event.value
    tag = STR_TAG
    if event.implicit[0]:
        for candidate, regexp in by_char.get(value[0] if value else "", wildcard):
            if regexp.match(value):
                tag = candidate
                break
    if tag == STR_TAG:
        return value
    if tag == FLOAT_TAG and FLOAT_CHARS.issuperset(value):
        return float(value)
    if tag == INT_TAG and value.isdigit() and (value[0] != "0" or value == "0"):
        return int(value)
    construct = loader.yaml_constructors.get(tag)
    if construct is None or tag == MERGE_TAG:
        raise NotPlain  # the full loader refuses an unknown tag or merges: let it
    return construct(loader, yaml.ScalarNode(tag, value))


def _build(loader, max_nesting: int, max_values: int) -> list:
    by_char, wildcard = _resolvers(type(loader))
    docs: list = []
    stack: list[list] = []   # per open container: [list or dict, pending key, has a pending key]
    events = 0
    get_event = loader.get_event
    while True:
        event = get_event()
        if event is None:
            return docs
        events += 1
        if events > max_values:
            raise NotPlain
        kind = type(event)
        if kind is ScalarEvent:
            value = _scalar(loader, event, by_char, wildcard)
        elif kind is SequenceStartEvent or kind is MappingStartEvent:
            if event.anchor is not None or event.tag not in NON_SPECIFIC or len(stack) >= max_nesting:
                raise NotPlain
            stack.append([[] if kind is SequenceStartEvent else {}, None, False])
            continue
        elif kind is SequenceEndEvent or kind is MappingEndEvent:
            value = stack.pop()[0]
        elif kind in (DocumentStartEvent, DocumentEndEvent, StreamStartEvent, StreamEndEvent):
            continue
        else:  # an alias
            raise NotPlain
        if not stack:
            docs.append(value)
            continue
        top = stack[-1]
        container = top[0]
        if type(container) is list:
            container.append(value)
        elif top[2]:
            container[top[1]] = value
            top[2] = False
        else:
            if kind is not ScalarEvent or value in container:
                raise NotPlain  # a complex key, or a duplicate one: the full loader reports it
            top[1], top[2] = value, True
