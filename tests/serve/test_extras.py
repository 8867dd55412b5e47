"""The base install stays light: the service and Ray are imported only when used."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from planarloc import extras
from planarloc.cli.main import build_parser, main


def test_cli_import_does_not_load_the_extras() -> None:
    code = (
        "import sys, planarloc.cli.main, planarloc.client, planarloc.distributed.ray_backend;"
        "extras = ('fastapi', 'uvicorn', 'ray', 'httpx', 'prometheus_client');"
        "loaded = [m for m in extras if m in sys.modules];"
        "print(loaded); sys.exit(1 if loaded else 0)"
    )
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root)
    assert r.returncode == 0, r.stdout + r.stderr


def test_missing_extra_is_one_line_naming_the_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    real = extras.importlib.import_module

    def fake(name: str):
        if name in ("uvicorn", "ray"):
            raise ImportError(f"No module named '{name}'")
        return real(name)

    monkeypatch.setattr(extras.importlib, "import_module", fake)
    (tmp_path / "m.db").write_bytes(b"x")
    assert main(["serve", "--map", str(tmp_path / "m.db")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'planarloc[serve]'" in err[0]
    from planarloc.distributed.ray_backend import RayBackend

    with pytest.raises(extras.MissingExtraError, match=r"pip install 'planarloc\[ray\]'"):
        RayBackend()


@pytest.mark.parametrize("argv", [["serve"], ["localize"]])
def test_help_has_an_example(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args([*argv, "--help"])
    out = capsys.readouterr().out
    assert "example" in out and ("--server" in out or "/v1/localize" in out)
