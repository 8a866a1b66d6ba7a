"""The README as a newcomer meets it: its first-session commands run, and the demo prints what it quotes.

The first-session block runs line by line in a fresh folder, with the synthetic sessions made
smaller (the commands are the README's; only --frames and --size change). The demo runs whole, as
`bash scripts/demo.sh` does on a fresh clone, into a folder of its own (DEMO_OUT), and its stdout
must be the README's block, up to run times and rates (which vary from run to run) and the output
folder's name.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def block_after(heading: str, fence: str) -> str:
    """The first ``fence`` code block after the line ``heading``."""
    after = README[README.index(heading):]
    match = re.search(rf"```{fence}\n(.*?)```", after, re.DOTALL)
    assert match, f"no ```{fence} block after {heading!r}"
    return match.group(1)


def env() -> dict[str, str]:
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}


def test_the_first_session_commands_run(tmp_path):
    lines = [line.split("  #")[0].strip() for line in block_after("## A first session", "bash").splitlines()]
    lines = [line for line in lines if line]
    assert len(lines) == 5 and lines[0].startswith("for ")
    for line in lines:
        command = re.sub(r"--frames \d+", "--frames 100", re.sub(r"--size \d+x\d+", "--size 192x108", line))
        proc = subprocess.run(["bash", "-c", command], cwd=tmp_path, env=env(), capture_output=True, text=True,
                              timeout=600)
        assert proc.returncode == 0, (command, proc.stdout, proc.stderr)
        assert "Traceback" not in proc.stderr
    assert (tmp_path / "results" / "cup_1.rrd").is_file() and (tmp_path / "model.json").is_file()
    assert "cup_3" in proc.stdout and "Macro" in proc.stdout  # the evaluate table


VARYING = re.compile(r"\d+(\.\d+)? (s|ms)\b|\d+(\.\d+)? frames/s")
NUMBER = re.compile(r"(?<![\w.])-?\d+\.\d+(?![\w.])")


def normalised(text: str, out: str) -> list[str]:
    """Lines with run times and rates replaced (they vary), the output folder named ``demo``."""
    return [VARYING.sub("#", line.replace(out, "demo")).rstrip() for line in text.strip().splitlines()]


def within_printed_precision(printed: list[str], quoted: list[str]) -> list[str]:
    """The lines that differ, a decimal number counting as equal within one unit of its last printed digit (the
    synthetic data's last bits, and so a figure's rounding, depend on the processor: docs/session.md); every
    other character, counts included, must be the same."""
    differ = [f"{len(printed)} lines, the README quotes {len(quoted)}"] if len(printed) != len(quoted) else []
    for mine, theirs in zip(printed, quoted):
        a, b = NUMBER.findall(mine), NUMBER.findall(theirs)
        same = NUMBER.sub("#", mine) == NUMBER.sub("#", theirs) and len(a) == len(b) and all(
            len(x.split(".")[1]) == len(y.split(".")[1])
            and abs(float(x) - float(y)) <= 1.000001 * 10.0 ** -len(x.split(".")[1]) for x, y in zip(a, b))
        if not same:
            differ.append(f"printed {mine!r}, quoted {theirs!r}")
    return differ


def test_decimals_count_as_equal_within_their_last_digit():
    assert within_printed_precision(["F1 0.945 / 0.970, 150 frames"], ["F1 0.946 / 0.970, 150 frames"]) == []
    assert within_printed_precision(["F1 0.945"], ["F1 0.947"]) != []  # two units of the last digit
    assert within_printed_precision(["0 flagged"], ["1 flagged"]) != []  # counts are exact
    assert within_printed_precision(["1.63   100%"], ["1.6   100%"]) != []  # the precision printed is part of it


@pytest.mark.skipif(os.environ.get("CONTACT_VIZ_SKIP_DEMO") == "1", reason="CONTACT_VIZ_SKIP_DEMO=1")
def test_the_demo_prints_what_the_readme_quotes(tmp_path):
    out = str(tmp_path / "demo")
    proc = subprocess.run(["bash", str(ROOT / "scripts" / "demo.sh")], cwd=ROOT, env={**env(), "DEMO_OUT": out},
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    quoted = block_after("## Current figures", "")
    assert within_printed_precision(normalised(proc.stdout, out), normalised(quoted, "demo")) == []
