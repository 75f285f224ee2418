"""The one base class every model Struct derives from.

`forbid_unknown_fields` turns a typo in a model file into an error instead of a silent
default; `kw_only` keeps field order free for defaults. Cross-field checks live in each
Struct's ``__post_init__`` and raise `ValueError`/`TypeError`, which msgspec reports with the
JSON path of the offending object (the YAML loader turns that into file:line:col).
"""

from __future__ import annotations

import msgspec


class Model(msgspec.Struct, forbid_unknown_fields=True, kw_only=True, omit_defaults=True):
    """Base of every model Struct."""


class FrozenModel(
    msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True, omit_defaults=True
):
    """Base of every immutable model Struct: `Model`'s settings, frozen (a frozen Struct may
    not derive from a mutable one)."""
