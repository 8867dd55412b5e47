"""Exit codes of every `planarloc` subcommand (documented in README, "Exit codes")."""

EXIT_OK = 0
EXIT_ERROR = 1  # bad input, bad file, damaged map: one line on stderr says which and why
EXIT_USAGE = 2  # bad command line (argparse)
EXIT_PARTIAL = 3  # some items (query or map images) could not be processed; results of all others written
EXIT_INTERRUPTED = 130

#: What Ctrl-C leaves, per command (the command's ``interrupted`` default; localize says it itself).
BUILD_RESUMES = "interrupted; re-run the same command to resume the build (the images stored so far are kept)"
EVALUATE_RESUMES = (
    "interrupted; the map built so far is kept: re-running the same command resumes its build and "
    "localizes the queries again"
)
DEMO_RESUMES = (
    "interrupted; re-running the same command reuses what is finished (the rendered world, the map "
    "built so far) and does the rest"
)
WARMUP_RESUMES = "interrupted; the kernels compiled so far are cached: re-run `planarloc warmup` for the rest"

HELP = (
    "exit codes:\n"
    "  0    everything was processed (failed localizations are results, listed as failed)\n"
    "  1    error: bad input, bad file, damaged map, unusable output; one line on stderr says\n"
    "       which and why; an earlier results file is left as it was\n"
    "  2    bad command line (usage)\n"
    "  3    partly done: some query images could not be processed (the results of all others\n"
    "       are written and each failure is recorded with its reason), or some map images were\n"
    "       left out of a map build (listed at the end)\n"
    "  130  interrupted (Ctrl-C); the message says what was kept (map build resumes when re-run)"
)


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, with the message saying what the command kept (printed by ``planarloc``)."""
