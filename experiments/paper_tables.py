"""Tables 2-4 of the paper beside ours, as markdown (``usp_jax.evaluation.paper_tables``). From the
repository root, after the evaluation and benchmark commands of RESULTS.md::

    python3 experiments/paper_tables.py --results experiments/results > experiments/results/paper_tables.md
"""

from usp_jax.evaluation.paper_tables import main

if __name__ == "__main__":
    main()
