"""Benchmark: skeletonization, skeleton graph and node classification (paper Alg. 1).

Cases
-----
* 2D AAA masks (the synthetic AAA projected through an AP C-arm) on 512x512 and 1024x1024
  frames: clean-up, thinning (default = half resolution above 400k box pixels, and full
  resolution for comparison), graph, classification, labelling.
* A 3D AAA lumen mask on a 512x512x300 grid (0.7 x 0.7 x 1.0 mm): 3D thinning, graph from
  the full volume, classification.
* A drawn ~1000-node 3D skeleton: graph + classification alone (the <= 20 ms goal).

Goals (issue 3): 2D 1024x1024 mask to classified graph <= 50 ms; 3D graph + classification
of a 1000-node skeleton <= 20 ms. Writes ``bench_skeleton.json`` and ``bench_skeleton.png``
to ``--out``. Run: ``.venv/bin/python Testing/benchmarks/bench_skeleton.py --out bench_out``.
"""

import json

import numpy as np

from FevarPlannerLib.graph import SkeletonGraph, classify, label_anatomy  # noqa: E402
from FevarPlannerLib.io import Volume  # noqa: E402
from FevarPlannerLib.projection import CArmGeometry, image_directions, projection_matrix_from_carm  # noqa: E402
from FevarPlannerLib.skeleton import clean_mask, skeletonize_2d, skeletonize_3d  # noqa: E402
from common import argument_parser, pyplot, save_figure, timed, write_report  # noqa: E402  (registers fixtures)
from fixtures import AAA_LINES, SAC_CENTRE, SAC_RADIUS, aaa_mask_2d, aaa_segments, draw_tubes  # noqa: E402


def median_ms(function, repeats):
    """Median wall time of ``function()`` in ms, and its last result."""
    times, result = [], None
    for _ in range(repeats):
        result, seconds, _ = timed(function)
        times.append(seconds * 1e3)
    return float(np.median(times)), result


def bench_2d(size, repeats):
    geometry = CArmGeometry(sid=1100.0, sod=750.0, pixel_spacing=(250.0 / size,) * 2, primary_angle=0.0,
                            secondary_angle=0.0, rows=size, cols=size)
    P = projection_matrix_from_carm(geometry, isocenter=(0.0, 0.0, 12.0))
    mask = aaa_mask_2d(P, (size, size))
    left, superior = image_directions(P, SAC_CENTRE)
    stages = {}
    stages["clean_mask"], _ = median_ms(lambda: clean_mask(mask, largest_component=False), repeats)
    stages["skeletonize_2d"], skeleton = median_ms(lambda: skeletonize_2d(mask), repeats)
    stages["skeletonize_2d_full_resolution"], full = median_ms(lambda: skeletonize_2d(mask, downsample=1), repeats)
    stages["graph"], graph = median_ms(lambda: SkeletonGraph.from_image(skeleton), repeats)
    stages["classify"], result = median_ms(lambda: classify(graph), repeats)
    stages["label"], _ = median_ms(lambda: label_anatomy(graph, result, left=left, superior=superior), repeats)
    stages["total_mask_to_labelled_graph"] = (stages["skeletonize_2d"] + stages["graph"] + stages["classify"]
                                              + stages["label"])
    return {"shape": [size, size], "mask_pixels": int(mask.sum()), "skeleton_nodes": len(graph),
            "skeleton_nodes_full_resolution": int(full.sum()), "branches": len(result.branches),
            "trunks": len(result.trunks), "median_ms": stages}


def aaa_volume_3d(shape=(300, 512, 512), spacing=(0.7, 0.7, 1.0)):
    """The synthetic AAA on a large grid, drawn only inside its bounding box."""
    centre_index = (np.array(shape[::-1]) - 1) / 2.0
    origin = -centre_index * np.array(spacing) + np.array([0.0, 0.0, 15.0])
    volume = Volume(np.zeros(shape, dtype=np.uint8), spacing, origin, np.eye(3))
    lo = volume.lps_to_index([-70.0, -40.0, -95.0]).astype(int)
    hi = volume.lps_to_index([70.0, 40.0, 125.0]).astype(int) + 1
    lo, hi = np.maximum(lo, 0), np.minimum(hi, shape)
    kji = np.indices(tuple(hi - lo)).reshape(3, -1).T + lo
    inside = draw_tubes(volume.index_to_lps(kji), aaa_segments(), (SAC_CENTRE, SAC_RADIUS))
    volume.array[tuple(kji[inside].T)] = 1
    return volume


def bench_3d(repeats):
    mask = aaa_volume_3d()
    stages = {}
    stages["skeletonize_3d"], skeleton = median_ms(lambda: skeletonize_3d(mask), 1)
    stages["graph_from_full_volume"], graph = median_ms(lambda: SkeletonGraph.from_volume(skeleton), repeats)
    indices = graph.grid_indices
    stages["graph_from_indices"], _ = median_ms(
        lambda: SkeletonGraph._from_grid(indices, skeleton.shape, skeleton.index_to_lps(indices), 1.0, True), repeats)
    stages["classify"], result = median_ms(lambda: classify(graph), repeats)
    stages["label"], _ = median_ms(lambda: label_anatomy(graph, result, left=(1, 0, 0), superior=(0, 0, 1)),
                                   repeats)
    return {"shape": list(mask.shape), "spacing_ijk_mm": mask.spacing.tolist(), "mask_voxels": int(mask.array.sum()),
            "skeleton_nodes": len(graph), "branches": len(result.branches), "trunks": len(result.trunks),
            "median_ms": stages}


def drawn_skeleton(scale=4):
    """The polyline AAA skeleton of test_graph.py drawn ``scale`` times finer (~1000 voxels)."""
    shape = (140 * scale, 12, 100 * scale)
    array = np.zeros(shape, dtype=np.uint8)
    for start, end in AAA_LINES:
        start, end = scale * np.asarray(start, float), scale * np.asarray(end, float)
        start[1] = end[1] = 5
        steps = int(np.abs(end - start).max())
        xyz = np.rint(start + np.linspace(0, 1, steps + 1)[:, None] * (end - start)).astype(int)
        array[xyz[:, 2], xyz[:, 1], xyz[:, 0]] = 1
    return Volume(array, [1.0 / scale] * 3, [0.0, 0.0, 0.0], np.eye(3))


def bench_graph_1000(repeats):
    skeleton = drawn_skeleton()
    stages = {}
    stages["graph"], graph = median_ms(lambda: SkeletonGraph.from_volume(skeleton), repeats)
    stages["classify"], result = median_ms(lambda: classify(graph), repeats)
    stages["label"], _ = median_ms(lambda: label_anatomy(graph, result, left=(1, 0, 0), superior=(0, 0, 1)),
                                   repeats)
    stages["total_graph_and_classification"] = stages["graph"] + stages["classify"] + stages["label"]
    return {"skeleton_nodes": len(graph), "branches": len(result.branches), "median_ms": stages}


def plot(results, path):
    fig, axes = pyplot().subplots(1, len(results), figsize=(4.2 * len(results), 4.2))
    for ax, (name, case) in zip(np.atleast_1d(axes), results.items()):
        stages = case["median_ms"]
        ax.barh(list(stages), list(stages.values()), color="tab:blue")
        ax.set_xscale("log")
        ax.set_xlabel("median time (ms)")
        ax.set_title(f"{name} ({case['skeleton_nodes']} nodes)", fontsize=9)
        ax.tick_params(axis="y", labelsize=7)
    save_figure(fig, path, dpi=120)


def main(argv=None):
    parser = argument_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--skip-3d", action="store_true", help="leave out the 512x512x300 thinning")
    args = parser.parse_args(argv)
    results = {
        "2d_512": bench_2d(512, args.repeats),
        "2d_1024": bench_2d(1024, args.repeats),
        "3d_graph_1000_nodes": bench_graph_1000(args.repeats),
    }
    if not args.skip_3d:
        results["3d_512x512x300"] = bench_3d(args.repeats)
    payload = {"repeats": args.repeats, "goals_ms": {"2d_1024_mask_to_classified_graph": 50.0,
                                                     "3d_graph_and_classification_1000_nodes": 20.0},
               "cases": results}
    args.out.mkdir(parents=True, exist_ok=True)
    write_report(args.out, "bench_skeleton", payload)
    plot(results, args.out / "bench_skeleton.png")
    print(json.dumps(payload, indent=2))


if __name__ == "__main__":
    main()
