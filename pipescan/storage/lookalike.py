"""Ids that look alike: NFKC folding, and letters of other scripts drawn like Latin ones.

An asset id is folded with Unicode NFKC when it is read (full-width ``ＭＨ１`` is ``MH1``), so
ids that differ only in compatibility forms are one asset. Letters of another script that are
drawn like Latin ones (Cyrillic ``МН`` against Latin ``MH``) are different characters and stay
so: :func:`lookalike_letters` finds them, so that the reader can warn that the id names another
asset than the one it looks like, and :func:`skeleton` maps an id to the Latin id it looks
like, to find such a twin among stored ids. It sits beside ``input`` and ``database``, which
both use it and stay apart.
"""

from __future__ import annotations

import unicodedata

__all__ = ["fold", "lookalike_letters", "skeleton"]

# Cyrillic and Greek letters drawn like a Latin letter (lower case: ids are case-folded first;
# Greek by its capital, which ids use: Η is H, Ν is N, Ρ is P).
_LATIN_LOOKALIKE = {
    **dict(zip("авекмнорстухіјѕԁԛԝ", "abekmhopctyxijsdqw", strict=True)),
    **dict(zip("αβεζηικμνορτυχ", "abezhikmnoptyx", strict=True)),
}


def fold(text: str) -> str:
    """``text`` in Unicode NFKC: compatibility forms (full-width, ligatures, superscripts) as
    their plain letters and digits.

    >>> fold("ＭＨ１-MH2")
    'MH1-MH2'
    """
    return unicodedata.normalize("NFKC", text)


def skeleton(text: str) -> str:
    """The Latin id ``text`` looks like: NFKC-folded, case-folded, look-alike letters of other
    scripts as the Latin ones.

    >>> skeleton("МН1-MH2") == skeleton("MH1-MH2")
    True
    """
    folded = fold(text).casefold()
    return "".join(_LATIN_LOOKALIKE.get(ch, ch) for ch in folded)


def lookalike_letters(text: str) -> list[str]:
    """The letters of ``text`` that are not Latin but are drawn like Latin ones.

    >>> lookalike_letters("МН1-MH2")
    ['М', 'Н']
    """
    return [ch for ch in text if ch.casefold() in _LATIN_LOOKALIKE]
