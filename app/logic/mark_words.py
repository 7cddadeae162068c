"""What the clinician reads about marks that are missing: sentences in the clinic's words, made
from the detector's typed result (the labels it lacks, the angles they hold back). The
detector's own line (pixels, candidate blobs, refusal reasons) stays for the engineer: the
window shows it as the sentence's detail, not as the sentence."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

from anklescan.core.vocabulary import LABELS, MARK_NAMES, MarkLabel


def _joined(words: Sequence[str]) -> str:
    """'a', 'a and b', 'a, b and c'."""
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def marks_named(labels: Iterable[MarkLabel | str]) -> str:
    """'mark 2 (front of the ankle)', 'marks 1 (front of the knee) and 5, 6 and 7 (table)':
    labels that share a name (the table's three) are named once."""
    ordered = sorted({int(label) for label in labels})
    if not ordered:
        return ""
    groups: dict[str, list[str]] = {}
    for label in ordered:
        groups.setdefault(MARK_NAMES[label], []).append(str(label))
    parts = [f"{_joined(numbers)} ({name})" for name, numbers in groups.items()]
    return ("mark " if len(ordered) == 1 else "marks ") + _joined(parts)


def missing_marks_sentence(missing: Iterable[MarkLabel | str]) -> str:
    """The banner's sentence after a scan whose marks were not all found automatically."""
    labels = {int(label) for label in missing}
    if labels >= set(LABELS):
        return "No mark was found automatically: place the seven in the 3-D view."
    if not labels:  # all seven labelled, yet the set needs a look (a mark too many, a doubtful one)
        return "The marks found automatically need checking: confirm or move them in the 3-D view."
    named, one = marks_named(labels), len(labels) == 1
    return (f"{named[:1].upper()}{named[1:]} {'was' if one else 'were'} not found automatically: "
            f"place {'it' if one else 'them'} in the 3-D view.")


def angles_not_computed(missing: Mapping[str, Sequence[MarkLabel | str]]) -> str:
    """'Leg inversion and leg plantar flexion need mark 2 (front of the ankle).': one sentence
    per set of marks the angles wait for ('' when every angle is computed)."""
    by_marks: dict[tuple[int, ...], list[str]] = {}  # RESULT.json's angle keys (SPEC §3) read as words
    for angle, labels in missing.items():
        by_marks.setdefault(tuple(sorted(int(lab) for lab in labels)), []).append(angle.replace("_", " "))
    sentences = []
    for labels, angles in by_marks.items():
        text = f"{_joined(angles)} need{'s' * (len(angles) == 1)} {marks_named(labels)}."
        sentences.append(text[:1].upper() + text[1:])
    return " ".join(sentences)
