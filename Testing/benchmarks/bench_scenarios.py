"""Independent-sets benchmark (issue 10): the scenarios phantom family through the case-folder route.

Writes the case folders of every independent set (FevarPlannerLib.scenarios: out-of-plane
bends at 0/5/10/20 degrees, wire straightening, clipped frames, distal forks the CT lacks,
wide sacs, extra branches, misaligned and angulated views, two views, patient-like anatomy:
coeliac, SMA, IMA, lumbars, internal iliacs and accessory renals in the CT and the frame, a
tortuous neck and looping iliacs; a bench phantom: a short pinhole (SOD 180-280 mm), a raw
thinned voxel skeleton as skeleton3d.nrrd and a JPEG-damaged 512 x 512 label), runs SV (rigid),
ICP-TPS and the proposed method on each with ``pipeline.plan_case`` and scores them with
the depth floor and the in-plane / along-ray split per vessel
(FevarPlannerLib.benchmark.run_independent_benchmark). Outputs in ``--out``:
``independent.json``, ``independent_table.md``, ``independent_sets.png``,
``independent_vessels.png`` and the case folders under ``cases/``. ``--kinds image_only``
runs the image-only cases (a CT and a DSA-like frame, segmented by the pipeline) beside the
same anatomies given as masks.

    .venv/bin/python Testing/benchmarks/bench_scenarios.py --out OUT [--quick] [--seed 0] [--kinds clipped two_views]
"""

from __future__ import annotations

from common import argument_parser, single_threaded_blas

single_threaded_blas()

from FevarPlannerLib.benchmark import run_independent_benchmark  # noqa: E402  (after the BLAS threads are set)
from FevarPlannerLib.cli import ProgressBar  # noqa: E402
from FevarPlannerLib.scenarios import KINDS  # noqa: E402


def main(argv=None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--quick", action="store_true", help="one case per set (about 1.5 minutes)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=None,
                        help="scenario kinds (default: all but image_only, whose CT segmentation is slow)")
    args = parser.parse_args(argv)
    summary = run_independent_benchmark(args.out, quick=args.quick, seed=args.seed, kinds=args.kinds,
                                        progress=ProgressBar())
    print((args.out / "independent_table.md").read_text())
    print(f"{summary['wall_s']:.0f} s; details in {args.out / 'independent.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
