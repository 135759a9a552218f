"""Issue 26: the README tells pip users how to get the CPU build of torch, next to the wheel."""

from __future__ import annotations

from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_gives_the_cpu_torch_install_next_to_the_wheel():
    text = README.read_text()
    cpu = text.index("pip install torch --index-url https://download.pytorch.org/whl/cpu")
    wheel = text.index("pip install beadsight-*.whl", cpu)
    assert 0 < wheel - cpu < 200  # the wheel's line follows the CPU torch line
