"""Machine facts: `egorefine info` and the dict CI and the benchmarks print."""

from __future__ import annotations

import torch

from egorefine.cli import main
from egorefine.core import machine_info


def test_machine_info_reports_the_libraries_and_threads_in_force(monkeypatch) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    info = machine_info()
    assert info["torch"] == torch.__version__ and info["torch_threads"] == torch.get_num_threads()
    assert info["env"]["OMP_NUM_THREADS"] == "3"
    assert "NUMBA_NUM_THREADS" not in info["env"]
    assert isinstance(info["cpu"], str) and info["cpu"]


def test_info_command_prints_one_line_per_entry(capsys) -> None:
    assert main(["info"]) == 0
    lines = capsys.readouterr().out.splitlines()
    names = [line.split(":", 1)[0] for line in lines]
    assert names == [*[k for k in machine_info() if k != "env"], "env"]
    assert f"torch: {torch.__version__}" in lines
