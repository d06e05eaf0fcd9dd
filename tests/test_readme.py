"""The README's API example runs as written and prints one line per frame."""

import contextlib
import io
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "the README has no python example"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(blocks[0], str(README), "exec"), {})
    lines = printed.getvalue().splitlines()
    assert len(lines) == 10 and lines[0].startswith("frame 0: stereo=True")
    epe = [float(re.search(r"EPE ([0-9.]+) px", line).group(1)) for line in lines]
    assert max(epe) < 1.0  # a sanity bound: realistic imaging at half size, not an accuracy target
