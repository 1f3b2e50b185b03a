"""Names people choose (clusters, credence labels): allowed characters and identity."""

from __future__ import annotations

import functools
import re
import unicodedata

#: Characters that print as nothing (zero-width spaces and joiners, the word joiner, the
#: byte-order mark, the soft hyphen, invisible operators): removed before names compare.
INVISIBLE = dict.fromkeys(
    map(
        ord,
        "\u00ad\u034f\u061c\u115f\u1160\u17b4\u17b5\u180e\u200b\u200c\u200d"
        "\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2060\u2061\u2062\u2063\u2064"
        "\u2066\u2067\u2068\u2069\u2800\u3164\ufeff\uffa0",
    ),
)
#: Blank characters of letter or symbol categories (braille blank, Hangul fillers).
_BLANKS = frozenset("\u115f\u1160\u2800\u3164\uffa0")
#: Categories refused in a name: format, control, private use, unassigned, surrogate,
#: line and paragraph separators.
_REFUSED_CATEGORIES = frozenset({"Cf", "Cc", "Co", "Cn", "Cs", "Zl", "Zp"})
#: Marks that change no letter: variation selectors and the combining grapheme joiner.
_SELECTORS = re.compile("[\u034f\u180b-\u180f\ufe00-\ufe0f\U000e0100-\U000e01ef]")
#: Names of the small capital letters (U+1D00 ``ᴀ``, U+0280 ``ʀ``, ...).
_SMALL_CAPITAL = re.compile(r"LATIN LETTER SMALL CAPITAL ([A-Z])")
#: Rounds of prototype mapping and case folding (a prototype may fold to a character that
#: has a prototype of its own: Cherokee ``Ꮯ`` -> ``C`` -> ``c``); two suffice, one more spare.
_SKELETON_ROUNDS = 3


def odd_character(name: str) -> str | None:
    """The first character a name may not hold, as ``U+2800 (BRAILLE ...)``; None if all may.

    Refused: `_REFUSED_CATEGORIES`, `_BLANKS` and `_SELECTORS`; combining accents stay allowed.
    """
    for char in name:
        category = unicodedata.category(char)
        if category in _REFUSED_CATEGORIES or char in _BLANKS or _SELECTORS.match(char):
            label = unicodedata.name(char, f"category {category}")
            return f"U+{ord(char):04X} ({label})"
    return None


def _homoglyphs(char: str) -> list[str]:
    """The characters Unicode's confusables data pairs with one character (maybe none)."""
    from confusable_homoglyphs import confusables  # here: it reads its 0.9 MB table

    found = confusables.is_confusable(char, greedy=True)
    return [glyph["c"] for glyph in found[0]["homoglyphs"]] if found else []


@functools.lru_cache(maxsize=8192)
def _prototype(char: str) -> str:
    """The prototype UTS #39 maps ``char`` to (``ս`` -> ``u``, ``0`` -> ``O``, ``m`` -> ``rn``).

    Of a prototype with a single such character both map to the smaller; a small capital
    letter, which the data leaves alone, maps to its letter.
    """
    small = _SMALL_CAPITAL.fullmatch(unicodedata.name(char, ""))
    if small:
        return small.group(1).lower()
    glyphs = _homoglyphs(char)
    if len(glyphs) != 1:
        return char  # not in the data, or a prototype of several characters
    (target,) = glyphs
    if len(target) == 1 and _homoglyphs(target) == [char]:
        return min(char, target)
    return target


def _fold(text: str) -> str:
    """NFKC, invisible characters and variation selectors removed, case folded."""
    text = unicodedata.normalize("NFKC", text).translate(INVISIBLE)
    return _SELECTORS.sub("", text).casefold()


def identity_key(name: str) -> str:
    """The identity a cluster name (or a credence label) is compared by.

    NFKC, invisible characters removed, case folded, each character replaced by its UTS #39
    prototype (``confusable_homoglyphs``), small capitals by their letters; ``_``, ``-`` and
    runs of spaces are one space. ``care``, ``CARE``, ``cаre`` (Cyrillic) and ``ᴄᴀʀᴇ`` are one.
    """
    text = _fold(name)
    for _ in range(_SKELETON_ROUNDS):
        mapped = _fold("".join(map(_prototype, text)))
        if mapped == text:
            break
        text = mapped
    return " ".join(text.replace("_", " ").replace("-", " ").split())
