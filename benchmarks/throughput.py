"""Particle-steps per second of the MPM step (the same as ``skfem-mpm bench``).

    python benchmarks/throughput.py [--quick] [--repeat 5] [--json] [--reference]
"""
import sys

from skfem_mpm.bench import main

if __name__ == "__main__":
    sys.exit(main())
