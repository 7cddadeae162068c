"""Typing help for OpenCV calls whose stubs are narrower than OpenCV itself.

OpenCV takes a plain number as the second operand of its per-element functions (``compare``,
``bitwise_or``, ``max``, ``divide`` ...: a scalar broadcast over the image), but its stubs type
that argument as an array only; ``scalar`` says so in one place instead of an ignore per call.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

if TYPE_CHECKING:
    from cv2.typing import MatLike


def scalar(value: float) -> MatLike:
    """``value`` as OpenCV's scalar operand (the stubs want an array; OpenCV takes a number)."""
    return cast("MatLike", value)


__all__ = ["scalar"]
