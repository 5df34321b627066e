"""What the smoothing controller's choices cost: its statistics against the default
`denoise` call and BNF, and each network pass with either vertex update, on an
81,920-face noisy icosphere (medians of 3 after a warm-up, one process).

    python benchmarks/controller_cost.py --controller runs/controller.npz   # make controller
    python benchmarks/controller_cost.py --weights W   # also W's default call (its controller)
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def median_time(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return sorted(times)[repeat // 2]


def main(argv=None) -> int:
    import trimesh

    import dmd_jax
    from dmd_jax.baselines import run_baseline
    from dmd_jax.controller import ControllerParams, decide
    from dmd_jax.inference import network_passes

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--controller", default="runs/controller.npz")
    parser.add_argument(
        "--weights",
        help="also time this weights file's default call (a milestone with its controller "
        "switched on) on the same mesh, and say what it chose",
    )
    args = parser.parse_args(argv)
    with np.load(args.controller) as z:
        fields = {k: z[k] for k in z.files}
    fields["options"] = fields["options"].tolist()
    ctrl = ControllerParams.from_dict(fields)

    sphere = trimesh.creation.icosphere(subdivisions=6)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    noisy = dmd_jax.add_noise(0, v, f, "gaussian", 0.2, units="edge", direction="normal")
    bundle = dmd_jax.load_pretrained()
    dmd_jax.denoise(noisy, f)
    default = median_time(lambda: dmd_jax.denoise(noisy, f))
    stats = median_time(lambda: decide(ctrl, noisy, f))
    run_baseline("bnf", noisy, f)
    bnf = median_time(lambda: run_baseline("bnf", noisy, f))
    print(
        f"{len(f):,} faces: default call {default:.3f} s, bnf {bnf:.3f} s, controller "
        f"statistics {stats:.3f} s ({100 * stats / default:.0f} % of the default call)"
    )
    if args.weights:
        other = dmd_jax.load_weights(args.weights)
        _, info = dmd_jax.denoise(noisy, f, other, return_info=True)
        took = median_time(lambda: dmd_jax.denoise(noisy, f, other))
        chose = info.controller or f"{info.passes} passes (no controller)"
        print(
            f"  {args.weights}: default call {took:.3f} s ({took / bnf:.2f}x bnf, "
            f"{took / default:.2f}x the bundled default); {chose}"
        )
    for update in ("jacobi", "solve"):
        b = bundle.with_vertex_update(update)

        def passes(k, b=b):
            return list(network_passes(noisy, f, b, k))

        passes(1)
        one, four = median_time(lambda: passes(1)), median_time(lambda: passes(4))
        print(
            f"  {update}: graph, frame and one pass {one:.3f} s; each further pass "
            f"{(four - one) / 3:.3f} s"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
