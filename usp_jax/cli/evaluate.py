"""``usp-jax evaluate --real PAIRS``: every method on pairs two real exposures made, at native
size (``usp_jax.evaluation.real_pairs``), as a table and, with ``--json``, a file written whole
or not at all."""

from __future__ import annotations

import json

from usp_jax.cli_track import _write_text
from usp_jax.evaluation import real_pairs


def run(args, methods) -> None:
    if not methods:
        raise ValueError("nothing to evaluate: --baselines-only with no --baselines")
    rows = real_pairs.evaluate_real(
        methods,
        args.real,
        top=args.top,
        nms=args.nms,
        ransac_orders=args.ransac_orders,
        progress=not args.no_progress,
    )
    print(f"{args.real}: real pairs at native size, top {args.top} points, NMS {args.nms}")
    print(real_pairs.format_real_table(rows))
    if args.json:
        config = {"top": args.top, "nms": args.nms, "ransac_orders": args.ransac_orders}
        _write_text(args.json, json.dumps(real_pairs.real_to_json(rows, config), indent=1))
        print(f"wrote {args.json}")
