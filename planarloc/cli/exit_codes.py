"""Exit codes of every `planarloc` subcommand (documented in README, "Exit codes")."""

EXIT_OK = 0
EXIT_ERROR = 1  # bad input, bad file, damaged map: one line on stderr says which and why
EXIT_USAGE = 2  # bad command line (argparse)
EXIT_PARTIAL = 3  # some items (query images) could not be processed; results of all others written
EXIT_INTERRUPTED = 130

HELP = ("exit codes:\n"
        "  0    everything was processed (failed localizations are results, listed as failed)\n"
        "  1    error: bad input, bad file, damaged map; one line on stderr says which and why\n"
        "  2    bad command line (usage)\n"
        "  3    partly done: some query images could not be processed; the results of all others\n"
        "       are written and each failure is recorded with its reason\n"
        "  130  interrupted (Ctrl-C); re-run the same command to resume")
