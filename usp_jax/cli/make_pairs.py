"""``usp-jax make-pairs``: HPatches-layout pairs from any folder of photos
(``evaluation.pairs.make_pairs``), turned or zoomed on request."""

from __future__ import annotations

from usp_jax.cli import arguments, outputs


def add_parser(subparsers) -> None:
    """The ``make-pairs`` subcommand: HPatches-layout pairs from a folder of photos."""
    p = subparsers.add_parser("make-pairs", help="HPatches-layout pairs from any folder of photos")
    p.add_argument(
        "--images",
        required=True,
        metavar="DIR",
        help="folder of photos, or 'sample' (the photos bundled with the installed packages);"
        " each gives a v_ (viewpoint) and an i_ (light) scene",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="folder for the v_*/i_* scenes (1.ppm ... N.ppm and the homographies H_1_k): new,"
        " empty, or an earlier make-pairs output (it holds make-pairs.json), which is replaced",
    )
    p.add_argument(
        "--size",
        type=arguments.resolution,
        default=(480, 640),
        metavar="HxW",
        help="size of every generated image (default 480x640)",
    )
    p.add_argument(
        "--views",
        type=arguments.positive,
        default=6,
        metavar="N",
        help="images per scene, 2 to 6 (default 6, as HPatches)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed, 0 to 2**32-1: the same seed and photos give the same pairs (default 0)",
    )
    turn = p.add_mutually_exclusive_group()
    turn.add_argument(
        "--rotation",
        type=float,
        metavar="DEG",
        help="also turn every viewpoint pair by an angle drawn uniformly from [-DEG, DEG]"
        " (0 to 180; 180: the full circle), positive counter-clockwise",
    )
    turn.add_argument(
        "--rotation-angles",
        type=float,
        nargs="+",
        metavar="DEG",
        help="the same with fixed angles in [-180, 180], used in turn, e.g. 0 45 90 135 180",
    )
    p.add_argument(
        "--zoom",
        type=arguments.zoom_range,
        metavar="MIN,MAX",
        help="also zoom every viewpoint pair by a factor drawn log-uniformly from [MIN, MAX],"
        " e.g. 0.5,2 (image 2's content magnified about its centre)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int | None:
    """Writes the pairs into ``--out`` (checked first: new, empty or an earlier output)."""
    from usp_jax.evaluation.pairs import make_pairs
    from usp_jax.inference.images import sample_photos

    outputs.check_output_folder(args.out, "--out")
    # 'sample': the photos bundled with the installed packages, as train's --data takes it.
    images = [path for _, path in sample_photos()] if args.images == "sample" else args.images
    scenes = make_pairs(
        images,
        args.out,
        seed=args.seed,
        size=args.size,
        num_views=args.views,
        rotation=args.rotation,
        rotation_angles=args.rotation_angles,
        zoom=args.zoom,
        progress=not args.no_progress,
    )
    print(f"wrote {len(scenes)} scenes to {args.out}")
