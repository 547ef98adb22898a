"""The key streams of a run: every random purpose of seed ``s`` has its own key.

``fold_in`` rather than ``split``: ``split(k, n)[i] == fold_in(k, i)`` with partitionable
threefry, and the consumers fold in small counters of their own (episode, cycle, round).
"""

from __future__ import annotations

import jax

_TAGS = {"collect": 0x636F6C6C, "neighbours": 0x6E656967, "train": 0x74726169,
         "resample": 0x72657361, "eval": 0x6576616C, "online": 0x6F6E6C6E,
         "relabel": 0x72656C61}


def purpose_key(seed: int, purpose: str) -> jax.Array:
    """The raw PRNG key of one purpose of seed ``seed``: ``collect``, ``neighbours``,
    ``train``, ``resample`` (fresh neighbourhood samples per cycle), ``eval`` or
    ``online`` (the online rounds' episodes)."""
    if purpose not in _TAGS:
        raise ValueError(f"unknown key purpose {purpose!r}; known: {sorted(_TAGS)}")
    return jax.random.fold_in(jax.random.PRNGKey(int(seed)), _TAGS[purpose])
