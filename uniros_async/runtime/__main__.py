"""A worker process's entry point: ``python -m uniros_async.runtime --uri-fd FD`` (started by ``launch.start_worker``).

Imports what every worker needs, then reads its ``WorkerSpec`` from stdin (and exits quietly if stdin closes
first), sends its listen URI on the pipe end ``FD`` and serves its supervisor until
told to close (``worker.worker_entry``). Not meant to be run by hand.
"""

from __future__ import annotations

import argparse
import multiprocessing.connection
import sys


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments, read the spec, run the worker."""
    parser = argparse.ArgumentParser(prog="python -m uniros_async.runtime", description=__doc__)
    parser.add_argument("--uri-fd", type=int, required=True, help="pipe end on which to send the listen URI")
    args = parser.parse_args(argv)
    from uniros_async.runtime.launch import read_spec
    from uniros_async.runtime.worker import worker_entry

    spec = read_spec(sys.stdin.buffer)
    if spec is None:  # discarded before it had a spec: the agent's checks of the env arguments failed
        return
    worker_entry(spec, multiprocessing.connection.Connection(args.uri_fd, readable=False))


if __name__ == "__main__":  # also imported by multiprocessing's spawn in a worker's own children: then not run
    main()
