"""The README's Python examples run as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def test_readme_python_blocks_run(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "the README should show the Python API"
    for block in blocks:
        exec(compile(block, str(README), "exec"), {})
    assert capsys.readouterr().out.strip()


def test_the_readme_analysis_script_says_in_one_line_that_a_dataset_is_missing(tmp_path):
    """``docs/analyze_dataset.py`` (the README's figure) on a bad path: one line and exit 2, as the CLI."""
    import subprocess
    import sys

    script = README.parent / "docs" / "analyze_dataset.py"
    for root, problem in ((tmp_path / "nope", "no such directory"), (tmp_path, "no manifest.json")):
        run = subprocess.run([sys.executable, str(script), str(root)], capture_output=True, text=True, cwd=tmp_path, check=False)
        assert run.returncode == 2, run.stderr
        assert run.stderr.startswith(f"error: {root}: {problem}") and run.stderr.count("\n") == 1, run.stderr
        assert not (tmp_path / "dataset_overview.png").exists()
