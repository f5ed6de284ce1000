"""The README's command-line examples hold: every option exists, the example password is
accepted, and the demo's simulate example makes videos of the demo rig's size.

The examples themselves (simulate, calibrate, analyze, admin) were run by hand from a
fresh data directory; this keeps what can be checked without minutes of video work.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def _commands() -> list[list[str]]:
    """Every ``bradyscope ...`` line of the README's code blocks, as words (continuations joined)."""
    blocks = re.findall(r"^```[^\n]*\n(.*?)^```", README, re.MULTILINE | re.DOTALL)
    out = []
    for block in blocks:
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            words = line.split("#", 1)[0].split()
            while words and words[0] != "bradyscope":
                words.pop(0)  # VAR=value prefixes, "source ..."
            if len(words) > 1:
                out.append(words)
    return out


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {s for a in parser._actions for s in a.option_strings}


def test_every_readme_command_and_option_exists() -> None:
    from app.cli import build_parser

    commands = _subparsers(build_parser())
    checked = 0
    for words in _commands():
        parser = commands.get(words[1])
        assert parser is not None, f"README: no command 'bradyscope {words[1]}'"
        rest = words[2:]
        actions = _subparsers(parser)
        # One parser per stretch: "admin list-users | deactivate-user EMAIL | ..." names several.
        stretches: list[list[str]] = [[]]
        for word in rest:
            if word == "|" and actions:
                stretches.append([])
            else:
                stretches[-1].append(word)
        for stretch in stretches:
            target = parser
            if actions:
                assert stretch and stretch[0] in actions, (
                    f"README: no 'bradyscope {words[1]} {stretch[:1]}'"
                )
                target = actions[stretch[0]]
            for word in stretch:
                flag = word.strip("[]()").split("=", 1)[0]
                if flag.startswith("--"):
                    assert flag in _options(target), f"README: {' '.join(words[:3])} has no {flag}"
                    checked += 1
    assert checked >= 20  # the synopsis and the examples name this many options at least


def test_the_readme_password_example_is_accepted() -> None:
    from app.passwords import check_password_strength

    match = re.search(r"BRADYSCOPE_PASSWORD=(\S+) bradyscope admin create-user (\S+)", README)
    assert match, "the README lost its create-user example"
    check_password_strength(match.group(1), email=match.group(2), min_length=15)


def test_the_demo_simulate_example_fits_the_demo_rig() -> None:
    from app.demo_plan import IMAGE_SIZE

    match = re.search(r"bradyscope simulate .*--size (\d+)x(\d+).*demo rig accepts", README)
    match = match or re.search(
        r"bradyscope simulate[^\n]*--size (\d+)x(\d+)[^\n]*fits the demo", README
    )
    assert match, "the README lost its simulate example for the demo"
    assert (int(match.group(1)), int(match.group(2))) == IMAGE_SIZE
