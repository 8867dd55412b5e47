"""Progress without a terminal: plain lines with elapsed times that include the whole stage."""

from __future__ import annotations

import io
import re
import threading
import time

from rich.console import Console

from planarloc.cli.progress import progress_reporter


def _lines(console: Console) -> list[str]:
    return console.file.getvalue().splitlines()  # type: ignore[attr-defined]


def test_plain_lines_when_not_a_terminal() -> None:
    console = Console(file=io.StringIO(), force_terminal=False, width=200)
    with progress_reporter(console, interval=0.2) as update:
        update("compile kernels", 0, 5)  # the stage starts: its clock starts here
        time.sleep(0.35)
        for i in range(1, 5):
            update("compile kernels", i, 5)  # the first of these is due (0.35 s > 0.2 s), the rest are not
        time.sleep(0.5)
        update("compile kernels", 5, 5)
        update("compile kernels", 5, 5)  # a repeated completion prints nothing more
        update("run steps", 3, 3)
    lines = _lines(console)
    assert lines[0] == "compile kernels: 0/5 (0 s)"
    assert lines[1] == "compile kernels: 1/5 (0 s)"
    done = re.fullmatch(r"compile kernels: 5/5, done in (\d+) s", lines[2])
    assert done and int(done.group(1)) in (0, 1)  # 0.85 s from the stage's first report
    assert lines[3:] == ["run steps: 3/3, done in 0 s"]


def test_elapsed_times_count_from_the_stage_start() -> None:
    console = Console(file=io.StringIO(), force_terminal=False, width=200)
    with progress_reporter(console, interval=0.0) as update:
        update("warm-up", 0, 2)
        time.sleep(1.1)  # a long first item (as a compile): the next line must show it
        update("warm-up", 1, 2)
    assert _lines(console)[1] == "warm-up: 1/2 (1 s)"


def test_updates_from_threads_print_whole_lines() -> None:
    console = Console(file=io.StringIO(), force_terminal=False, width=200)
    with progress_reporter(console, interval=0.0) as update:
        threads = [
            threading.Thread(target=lambda k=k: [update(f"stage {k}", i, 50) for i in range(51)])
            for k in range(4)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    lines = _lines(console)
    assert len(lines) == 4 * 51 and all(
        re.fullmatch(r"stage \d: \d+/50( \(0 s\)|, done in 0 s)", x) for x in lines
    )
