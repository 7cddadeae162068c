"""The command line explains itself (issue 42): every argument of `measure` has a text, and the
top-level help calls `demo` what it is."""

import argparse

from anklescan.app.cli import build_parser


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_measure_help_describes_every_argument():
    measure = _subparsers(build_parser())["measure"]
    undocumented = [a.dest for a in measure._actions if not a.help]
    assert undocumented == []
    text = measure.format_help()
    assert "RESULT.json" in text and "capture folder" in text and "calibration JSON" in text


def test_top_level_help_calls_demo_a_simulated_study():
    text = build_parser().format_help()
    demo_line = " ".join(text[text.index("demo  "):].split()[:12])
    assert "simulated study" in demo_line and "a whole clinical session" not in demo_line
