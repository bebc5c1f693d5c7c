"""Logging set-up for stage scripts: messages with timestamps to a log file and to stderr."""

from __future__ import annotations

import logging
import sys


def setup_logging(log_file: str | None = None, level: int = logging.INFO) -> None:
    """Send log records to stderr and ``log_file``; an exception that ends the script goes to both
    as well (Snakemake points at the job's log file when a job fails)."""
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if log_file:
        handlers.append(logging.FileHandler(log_file, mode="w"))
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        handlers=handlers, force=True)

    def log_uncaught(kind, value, tb):
        if issubclass(kind, KeyboardInterrupt):
            sys.__excepthook__(kind, value, tb)
            return
        logging.getLogger("stex").critical("the stage failed: %s: %s", kind.__name__, value,
                                           exc_info=(kind, value, tb))

    sys.excepthook = log_uncaught
