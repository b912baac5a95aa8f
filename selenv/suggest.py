"""Suggestions for mistyped names ("did you mean"): env ids, agent names and keywords.

One wording everywhere, built on :func:`difflib.get_close_matches`::

    >>> did_you_mean("gredy", ["greedy", "random", "swap"])
    "did you mean 'greedy'?"
    >>> did_you_mean("xyz", ["greedy", "random"])
    ''
    >>> with_suggestion("unknown agent 'gredy'", "gredy", ["greedy"], "agents: greedy")
    "unknown agent 'gredy'; did you mean 'greedy'? agents: greedy"
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence

__all__ = ["close_matches", "did_you_mean", "did_you_mean_each", "with_suggestion"]

#: similarity ratio (difflib's) below which a known name is not suggested
CUTOFF = 0.6
#: suggestions whose ratio is this much below the best one's are left out
MARGIN = 0.1
#: at most this many suggestions
MAX_SUGGESTIONS = 3


def close_matches(word: str, choices: Iterable[str], n: int = MAX_SUGGESTIONS) -> list[str]:
    """The known names closest to ``word``, best first; none if nothing is close.

    At most ``n`` names, each within :data:`MARGIN` of the best one's similarity (``gredy``
    gives ``greedy``, not also ``lazy_greedy``). The comparison ignores case
    (``fimselection`` finds ``FIMSelection``); the names are returned as spelled in
    ``choices``, and never ``word`` itself.

    Raises:
        TypeError: ``word`` is not a str.
    """
    if not isinstance(word, str):
        raise TypeError(f"word must be a str, got {type(word).__name__}")
    by_folded: dict[str, str] = {}
    for choice in map(str, choices):
        if choice != word:
            by_folded.setdefault(choice.casefold(), choice)
    folded = word.casefold()
    found = difflib.get_close_matches(folded, list(by_folded), n=n, cutoff=CUTOFF)
    if not found:
        return []

    def ratio(candidate: str) -> float:
        return difflib.SequenceMatcher(None, folded, candidate).ratio()

    best = ratio(found[0])
    return [by_folded[f] for f in found if ratio(f) >= best - MARGIN]


def _alternatives(names: Sequence[str]) -> str:
    quoted = [repr(n) for n in names]
    return quoted[0] if len(quoted) == 1 else f"{', '.join(quoted[:-1])} or {quoted[-1]}"


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"did you mean 'a'?"`` / ``"did you mean 'a' or 'b'?"``, or ``""`` if nothing is close."""
    found = close_matches(word, choices)
    return f"did you mean {_alternatives(found)}?" if found else ""


def did_you_mean_each(words: Sequence[str], choices: Iterable[str]) -> str:
    """One "did you mean" for several unknown ``words``, or ``""`` if nothing is close to any.

    One word reads as :func:`did_you_mean`; several as ``"did you mean 'budget' for
    'budgt', 'sensors' for 'senors'?"`` (words without a close name are left out).
    """
    if len(words) == 1:
        return did_you_mean(words[0], choices)
    known = list(choices)
    pairs = [(w, found) for w in words if (found := close_matches(w, known))]
    if not pairs:
        return ""
    return "did you mean " + ", ".join(f"{_alternatives(f)} for {w!r}" for w, f in pairs) + "?"


def with_suggestion(
    message: str, word: str | Sequence[str], choices: Iterable[str], then: str = ""
) -> str:
    """``message`` + ``"; did you mean ...?"`` when a known name is close to ``word``, + ``then``.

    ``word`` may be several unknown words (:func:`did_you_mean_each`). ``then`` (e.g. the list
    of the known names) follows the question after a space, or ``message`` after ``"; "``.
    """
    words = [word] if isinstance(word, str) else list(word)
    hint = did_you_mean_each(words, choices)
    parts = [message, f"{hint} {then}".strip() if hint else then]
    return "; ".join(p for p in parts if p)
