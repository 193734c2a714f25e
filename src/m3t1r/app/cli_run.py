"""One verb's run under the command line's rules: exit statuses, Ctrl-C and SIGTERM, BLAS threads, --quiet.

`m3t1r.app.cli.main` parses the arguments (argparse alone), imports the verb's module and hands
both here; this module imports what a run needs and a bare `--help` does not (numpy with the errors).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from m3t1r._threads import single_blas_thread
from m3t1r.app.cli_common import RowFailures
from m3t1r.calibration.assessment import FitRejected
from m3t1r.errors import M3t1rError
from m3t1r.io.outputs import interrupted_outputs
from m3t1r.io.progress import set_quiet
from m3t1r.io.signals import Terminated, termination_as_exception
from m3t1r.io.temporaries import remove_live_temporaries

__all__ = ["EXIT_ERROR", "EXIT_ROWS_FAILED", "run_verb"]

EXIT_ERROR, EXIT_ROWS_FAILED = 2, 1


def run_verb(run: Callable[[argparse.Namespace], None], args: argparse.Namespace) -> int:
    """Run `run(args)`; returns the exit status, the error printed as `m3t1r: error: ...` (no traceback)."""
    set_quiet(getattr(args, "quiet", False))
    try:
        # SIGTERM/SIGHUP unwind like Ctrl-C, so every OutputSet removes its temporary files. The
        # BLAS limit is set after the verb's module is imported: it applies to the libraries loaded.
        with termination_as_exception(), single_blas_thread():
            run(args)
    except (RowFailures, FitRejected) as exc:
        print(f"m3t1r: error: {exc}", file=sys.stderr)
        return EXIT_ROWS_FAILED
    except (M3t1rError, OSError) as exc:
        print(f"m3t1r: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except MemoryError:
        # numpy raises it for one array too large for this machine (a plan of 10^5 poses, a huge read):
        # the run is refused like any other input it cannot take, with nothing written.
        print(
            f"m3t1r: error: {args.verb}: not enough memory for this input on this machine; nothing was written "
            "(split the input, or ask for fewer poses or candidates)",
            file=sys.stderr,
        )
        return EXIT_ERROR
    except KeyboardInterrupt as exc:
        print(f"m3t1r: interrupted; {interrupted_outputs(exc)}", file=sys.stderr)
        return 130
    except Terminated as exc:
        print(f"m3t1r: {exc}; {interrupted_outputs(exc)}", file=sys.stderr)
        return 128 + exc.signum
    finally:
        set_quiet(False)
        remove_live_temporaries()  # a failed command's claims, in this process too (tests, the demo)
    return 0
