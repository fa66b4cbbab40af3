"""Reproduce the paper's accuracy and ADI tables: ``mitsuba-p3 reproduce`` with the same options.

    python scripts/reproduce_tables.py [--data data] [--out results] [--benchmarks fsclvr,room,dark,ood]
        [--likelihoods p3,np3] [--episodes 100] [--jobs CORES] [--chains 8 --steps 200 ...] [--sigma S]
        [--distance all|colour+class|...] [--spread-shots 3]

See :mod:`mitsuba_p3.reproduce` for what it writes and how it resumes.
"""
import sys

from mitsuba_p3.cli import main

if __name__ == "__main__":
    sys.argv = ["mitsuba-p3", "reproduce", *sys.argv[1:]]
    main()
