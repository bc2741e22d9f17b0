"""Run by conftest.render_cases: several ``massview render`` command lines in one process, under
``mpiexec -n N`` (each is collective on every rank, as ``mpiexec -n N massview render ...``
runs it) or, for one rank, without MPI (as ``massview render`` runs it). One job instead of one
per case saves the ranks' start-up (Python, numpy, GL, MPI: 1-2 s each on a 2-core host); every
case still renders, compares with the reference and writes its outputs as the CLI does.

argv[1]: a JSON file ``[[case name, [render args...]], ...]``. Rank 0 prints ``case NAME`` before
each case and ``cases ok`` at the end; a case that fails ends the job (status != 0), its error
printed by the failing rank, so the last ``case`` line names it."""

import json
import sys

from massview.app.cli import main
from massview.parallel.runtime import in_mpi_job, world


def run(cases_file: str) -> int:
    comm = world() if in_mpi_job() else None
    rank = comm.Get_rank() if comm is not None else 0
    with open(cases_file) as f:
        cases = json.load(f)
    for name, args in cases:
        if rank == 0:
            print(f"case {name}", flush=True)
        rc = main(["render", *args])
        if rc != 0:
            print(f"case {name} failed with status {rc} on rank {rank}", file=sys.stderr, flush=True)
            if comm is not None and comm.Get_size() > 1:
                comm.Abort(rc)
            return rc
    if comm is not None:
        comm.Barrier()
    if rank == 0:
        print("cases ok", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run(sys.argv[1]))
