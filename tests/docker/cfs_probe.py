"""CPU-bound probe run inside a CPU-limited container: wall vs CPU time of a fixed ~70 ms job.

Prints one JSON object: the CPU and wall seconds of each repetition. Used by
tests/docker/test_docker_launcher.py::test_cfs_wall_time_tracks_quota and by hand:
``docker run --rm --cpu-period 10000 --cpu-quota 2500 -v $PWD/tests/docker:/p:ro
cosim5g/runtime:latest python /p/cfs_probe.py 15``.
"""

import json
import random
import sys
import time

TARGET_CPU_S = 0.070  # docs/architecture.md sec. 5 measured a 68 ms job


def work(n: int) -> int:
    x = 0
    for i in range(n):
        x += i * i
    return x


def main() -> None:
    reps = int(sys.argv[1]) if len(sys.argv) > 1 else 15
    rng = random.Random(1)
    n = 20_000
    while True:  # calibrate on CPU time, which the quota does not distort
        c0 = time.process_time()
        work(n)
        dc = time.process_time() - c0
        if dc > 0.05:
            break
        n *= 2
    n = int(n * TARGET_CPU_S / dc)
    cpu, wall = [], []
    for _ in range(reps):
        # A random idle gap puts the job's start at a random phase of the CFS period, as a
        # federate's jobs are.
        time.sleep(rng.uniform(0.02, 0.12))
        w0, c0 = time.perf_counter(), time.process_time()
        work(n)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    print(json.dumps({"cpu_s": cpu, "wall_s": wall}), flush=True)


if __name__ == "__main__":
    main()
