"""Names people choose (moral clusters, credence labels): which characters, which identity.

Two rules, one for each way a name can deceive:

- :func:`odd_character` refuses the characters that print as nothing or change another
  character's look: format characters (Unicode category ``Cf``: zero-width spaces and
  joiners, bidirectional controls, the tag characters U+E0000-U+E007F), controls, private
  use, unassigned and surrogate code points, line and paragraph separators, variation
  selectors and the combining grapheme joiner (``Mn`` marks that alter no letter's
  meaning), and the blank characters of other categories (U+2800 braille blank, the Hangul
  fillers, U+3164, U+FFA0). Combining accents stay allowed (``café`` written with U+0301).
- :func:`identity_key` is the identity two names are compared by: the UTS #39 skeleton
  (through the ``confusable-homoglyphs`` package), after NFKC and case folding, with the
  small capital letters (``ᴄᴀʀᴇ``), which confusables.txt does not map, read as their
  letters.
"""

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
    """The first character of ``name`` a name may not hold, as ``U+2800 (BRAILLE ...)``.

    Returns:
        None when every character may be in a name; otherwise the code point and its
        Unicode name (or category, for one without a name).

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

    ``confusable_homoglyphs`` holds Unicode's ``confusables.txt`` as a graph: a character
    that has a prototype lists that one alone; a prototype lists the characters mapped to
    it. A prototype with a single such character reads like one, so of such a pair both
    map to the smaller: the key is the same either way. A small capital letter, which the
    data leaves alone, maps to its letter.
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

    NFKC (full-width, mathematical and other compatibility forms become plain letters),
    invisible characters and variation selectors removed, case folded, and every character
    replaced by its prototype of Unicode's confusables (the skeleton of UTS #39, "Unicode
    Security Mechanisms", from the ``confusable_homoglyphs`` package): Cyrillic, Greek,
    Armenian, Cherokee and other look-alikes of Latin letters become those letters (and
    ``0`` becomes ``O``, ``1`` and ``I`` become ``l``, ``m`` becomes ``rn``, as UTS #39
    says), small capitals their letters; ``_``, ``-`` and runs of spaces count as one
    space. ``care``, ``CARE``, ``ｃａｒｅ``, ``ca\u200bre``, ``cаre`` (a Cyrillic ``а``),
    ``ᏟᎪᏒᎬ`` (Cherokee) and ``ᴄᴀʀᴇ`` (small capitals) are one identity.
    """
    text = _fold(name)
    for _ in range(_SKELETON_ROUNDS):
        mapped = _fold("".join(map(_prototype, text)))
        if mapped == text:
            break
        text = mapped
    return " ".join(text.replace("_", " ").replace("-", " ").split())
