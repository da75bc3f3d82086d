"""Joseph's method with the bilinear loads as hardware vector gathers, against the shipped kernel.

numba exposes no vector types, so the march of eight rays (lanes) is written as LLVM IR in a
numba intrinsic: each step computes the eight fixed-point positions as one vector and loads the
four neighbours through ``llvm.masked.gather`` (lanes past their ray's end masked off, so they
read nothing), either as four gathers of floats (``floats``: vgatherqps on AVX-512) or as two
gathers of the 64-bit neighbour pairs split in registers (``pairs``: vpgatherqq). Everything
else (ray set-up, leaps over empty space, the ends' integral) is the shipped kernel's, and the
DRRs must come out identical bit for bit (each lane sums its own samples in order).

Prints JSON lines: the check, then per round the least and median microseconds per call of
each kernel (the bench volume and geometry, field mask on; rounds alternate the kernels),
serial and on the process's threads, and ns per bilinear sample with every lane busy.

    PYTHONPATH=. python scripts/gather_kernel_ab.py --rounds 5
"""

from __future__ import annotations

import argparse
import json
import time

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from registration.core import drr as drr_module
from registration.core.blas import one_blas_thread
from registration.core.drr_kernels import _KERNEL_FASTMATH, _ends, _march_two, _set_up_row
from registration.studies.perf import bench_geometry, bench_volume

LANES = 8
_FLAGS = tuple(sorted(_KERNEL_FASTMATH))


def _lanes_intrinsic(pairs: bool):  # noqa: ANN202 - a numba intrinsic
    """The lane march: ``st`` int64 (6, LANES) rows x, q, x step, q step, q stride, index of the
    sample after the last (-1: an idle lane); ``out`` float32 (5, LANES) rows: the sum of the
    samples 1 .. last, and the samples before, first, last and after."""

    @intrinsic
    def march_lanes(typingctx, arr, st, out, nmax):  # noqa: ANN001, ANN202, ARG001
        def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
            a = context.make_array(signature.args[0])(context, builder, args[0])
            s = context.make_array(signature.args[1])(context, builder, args[1])
            o = context.make_array(signature.args[2])(context, builder, args[2])
            i1, i32, i64, f32 = ir.IntType(1), ir.IntType(32), ir.IntType(64), ir.FloatType()
            v64, v32, vf, vb = (ir.VectorType(t, LANES) for t in (i64, i32, f32, i1))

            def splat(value, vtype):  # noqa: ANN001, ANN202
                return ir.Constant(vtype, [value] * LANES)

            def broadcast(scalar):  # noqa: ANN001, ANN202
                v = builder.insert_element(ir.Constant(v64, ir.Undefined), scalar, ir.Constant(i32, 0))
                return builder.shuffle_vector(v, ir.Constant(v64, ir.Undefined), ir.Constant(v32, [0] * LANES))

            def row(k: int):  # noqa: ANN202
                p = builder.gep(s.data, [ir.Constant(i64, k * LANES)], source_etype=i64)
                return builder.load(builder.bitcast(p, v64.as_pointer()), typ=v64, align=8)

            def gather(name: str, elem, addresses, on):  # noqa: ANN001, ANN202
                vptr = ir.VectorType(elem.as_pointer(), LANES)
                vtype = ir.VectorType(elem, LANES)
                fn = builder.module.globals.get(name) or ir.Function(
                    builder.module, ir.FunctionType(vtype, [vptr, i32, vb, vtype]), name=name
                )
                zero = ir.Constant(vtype, [0.0 if elem == f32 else 0] * LANES)
                return builder.call(fn, [builder.inttoptr(addresses, vptr), ir.Constant(i32, 4), on, zero])

            def neighbours(address, on):  # noqa: ANN001, ANN202
                if not pairs:
                    name = f"llvm.masked.gather.v{LANES}f32.v{LANES}p0"
                    return gather(name, f32, address, on), gather(name, f32, builder.add(address, splat(4, v64)), on)
                both = builder.bitcast(gather(f"llvm.masked.gather.v{LANES}i64.v{LANES}p0", i64, address, on),
                                       ir.VectorType(f32, 2 * LANES))  # fmt: skip
                even = ir.Constant(v32, list(range(0, 2 * LANES, 2)))
                odd = ir.Constant(v32, list(range(1, 2 * LANES, 2)))
                return builder.shuffle_vector(both, both, even), builder.shuffle_vector(both, both, odd)

            x0, q0, rx, rq, usq, last = (row(k) for k in range(6))
            base = broadcast(builder.ptrtoint(a.data, i64))
            zero_f, one = splat(0.0, vf), splat(1, v64)
            pre = builder.block
            loop = builder.append_basic_block("lanes.loop")
            done = builder.append_basic_block("lanes.done")
            builder.branch(loop)
            builder.position_at_end(loop)
            step, x, q = builder.phi(i64), builder.phi(v64), builder.phi(v64)
            acc, before, first, final, after = (builder.phi(vf) for _ in range(5))
            sv = broadcast(step)
            on = builder.icmp_signed("<=", sv, last)
            low = splat((1 << 32) - 1, v64)
            scale = splat(float(np.float32(1.0 / 2**32)), vf)
            fp = builder.fmul(builder.uitofp(builder.trunc(builder.and_(x, low), v32), vf), scale, flags=_FLAGS)
            fq = builder.fmul(builder.uitofp(builder.trunc(builder.and_(q, low), v32), vf), scale, flags=_FLAGS)
            index = builder.add(builder.mul(builder.lshr(q, splat(32, v64)), usq), builder.lshr(x, splat(32, v64)))
            address = builder.add(base, builder.shl(index, splat(2, v64)))
            v00, v10 = neighbours(address, on)
            v01, v11 = neighbours(builder.add(address, builder.shl(usq, splat(2, v64))), on)

            def lerp(lo, hi, f):  # noqa: ANN001, ANN202
                return builder.fadd(lo, builder.fmul(f, builder.fsub(hi, lo, flags=_FLAGS), flags=_FLAGS), flags=_FLAGS)

            v = lerp(lerp(v00, v10, fp), lerp(v01, v11, fp), fq)
            inner = builder.and_(builder.icmp_signed(">=", sv, one), builder.icmp_signed("<", sv, last))
            updates = (
                (acc, builder.select(inner, builder.fadd(acc, v, flags=_FLAGS), acc)),
                (before, builder.select(builder.icmp_signed("==", sv, splat(0, v64)), v, before)),
                (first, builder.select(builder.icmp_signed("==", sv, one), v, first)),
                (final, builder.select(builder.icmp_signed("==", builder.add(sv, one), last), v, final)),
                (after, builder.select(builder.icmp_signed("==", sv, last), v, after)),
            )
            x_next = builder.select(on, builder.add(x, rx), x)
            q_next = builder.select(on, builder.add(q, rq), q)
            step_next = builder.add(step, ir.Constant(i64, 1))
            end = builder.block
            builder.cbranch(builder.icmp_signed("<=", step_next, args[3]), loop, done)
            for phi, start, nxt in ((step, ir.Constant(i64, 0), step_next), (x, x0, x_next), (q, q0, q_next)):
                phi.add_incoming(start, pre)
                phi.add_incoming(nxt, end)
            for phi, nxt in updates:
                phi.add_incoming(zero_f, pre)
                phi.add_incoming(nxt, end)
            builder.position_at_end(done)
            for k, (_, value) in enumerate(updates):
                p = builder.gep(o.data, [ir.Constant(i64, k * LANES)], source_etype=f32)
                builder.store(value, builder.bitcast(p, vf.as_pointer()), align=4)
            return context.get_dummy_value()

        return types.void(arr, st, out, nmax), codegen

    return march_lanes


def _lanes_kernel(march_lanes, parallel: bool):  # noqa: ANN001, ANN202
    def joseph_lanes(mu, mu_t, shape_ijk, lo, hi, source, a_mat, i2w, mask, use_mask, empty, empty_strides,
                     use_empty, out, work):  # noqa: ANN001, ANN202  # fmt: skip
        rows, cols = out.shape
        for r in numba.prange(rows):
            ints = np.empty((cols, 9), dtype=np.int64)
            reals = np.empty((cols, 3), dtype=np.float64)
            where = np.empty(cols, dtype=np.int64)
            order = np.empty(cols, dtype=np.int64)
            st = np.empty((6, LANES), dtype=np.int64)
            lane_out = np.empty((5, LANES), dtype=np.float32)
            n_rays = _set_up_row(r, a_mat, source, lo, hi, shape_ijk, i2w, mask, use_mask, empty, empty_strides,
                                 use_empty, out, ints, reals, where)  # fmt: skip
            n_mu = 0  # the rays reading mu first, then those reading mu_t
            for n in range(n_rays):
                if ints[n, 0] == 0:
                    order[n_mu] = n
                    n_mu += 1
            k = n_mu
            for n in range(n_rays):
                if ints[n, 0] != 0:
                    order[k] = n
                    k += 1
            samples = 0
            for group in range(2):
                g0 = 0 if group == 0 else n_mu
                g1 = n_mu if group == 0 else n_rays
                arr = mu if group == 0 else mu_t
                for b in range(g0, g1, LANES):
                    nmax = 0
                    for lane in range(LANES):
                        if b + lane < g1:
                            n = order[b + lane]
                            for k in range(5):
                                st[k, lane] = ints[n, k + 1]
                            st[5, lane] = ints[n, 6] + 2
                            nmax = max(nmax, ints[n, 6] + 2)
                        else:
                            for k in range(5):
                                st[k, lane] = 0
                            st[5, lane] = -1
                    march_lanes(arr, st, lane_out, nmax)
                    for lane in range(min(LANES, g1 - b)):
                        n = order[b + lane]
                        total = _ends(lane_out[1, lane], lane_out[2, lane], lane_out[3, lane], lane_out[4, lane],
                                      lane_out[0, lane], reals[n, 0], reals[n, 1], ints[n, 7], ints[n, 8])  # fmt: skip
                        out[r, where[n]] = total * np.float32(reals[n, 2])
                        samples += ints[n, 6] + 3
            work[r] = samples

    return numba.njit(parallel=parallel, fastmath=_KERNEL_FASTMATH, nogil=True)(joseph_lanes)


def _busy_lanes(march_lanes):  # noqa: ANN001, ANN202
    """A measurement: ns per bilinear sample with every lane busy (127 samples each), against the
    shipped pair march on the same rays."""

    @numba.njit(fastmath=_KERNEL_FASTMATH)
    def lanes(arr, st, out, reps):  # noqa: ANN001, ANN202
        total = 0.0
        for _ in range(reps):
            march_lanes(arr, st, out, 126)
            total += out[0, 0]
        return total

    @numba.njit(fastmath=_KERNEL_FASTMATH)
    def scalar(arr, st, reps):  # noqa: ANN001, ANN202
        total = 0.0
        for _ in range(reps):
            for lane in range(0, LANES, 2):
                a = (True, False, st[0, lane], st[1, lane], st[2, lane], st[3, lane], st[4, lane], 124, 0.0, 126.0,
                     1, 125, 1.0)  # fmt: skip
                b = (True, False, st[0, lane + 1], st[1, lane + 1], st[2, lane + 1], st[3, lane + 1], st[4, lane + 1],
                     124, 0.0, 126.0, 1, 125, 1.0)  # fmt: skip
                ta, tb = _march_two(arr, a, arr, b)
                total += ta + tb
        return total

    n = 132
    rng = np.random.default_rng(0)
    arr = rng.random(n**3).astype(np.float32)
    st = np.zeros((6, LANES), np.int64)
    st[0] = ((n * n * 2 + n * rng.integers(2, 100, LANES) + rng.integers(2, 100, LANES)) << 32) + rng.integers(
        0, 2**32, LANES
    )
    st[2] = ((n * n) << 32) + rng.integers(-(2**30), 2**30, LANES)
    st[4] = n
    st[5] = 126
    out = np.zeros((5, LANES), np.float32)
    lanes(arr, st, out, 1)
    scalar(arr, st, 1)

    def measure(reps: int = 20000) -> tuple[float, float]:
        t0 = time.perf_counter()
        lanes(arr, st, out, reps)
        t1 = time.perf_counter()
        scalar(arr, st, reps)
        t2 = time.perf_counter()
        samples = reps * LANES * 127
        return 1e9 * (t1 - t0) / samples, 1e9 * (t2 - t1) / samples

    return measure


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--calls", type=int, default=30)
    parser.add_argument("--image-px", type=int, default=128)
    parser.add_argument("--volume-px", type=int, default=128)
    args = parser.parse_args()
    volume, geometry = bench_volume(args.volume_px), bench_geometry(args.image_px)
    renderer = drr_module.DRRRenderer(volume, levels=1)
    mask = geometry.field_mask()
    shipped = {"parallel": drr_module._render_joseph, "serial": drr_module._render_joseph_serial}
    arms = {"shipped": shipped}
    for mode in ("floats", "pairs"):
        march = _lanes_intrinsic(mode == "pairs")
        arms[mode] = {"parallel": _lanes_kernel(march, True), "serial": _lanes_kernel(march, False),
                      "busy": _busy_lanes(march)}  # fmt: skip

    def use(kernels: dict) -> None:
        drr_module._render_joseph, drr_module._render_joseph_serial = kernels["parallel"], kernels["serial"]

    def call(kernels: dict, parallel: bool) -> np.ndarray:
        use(kernels)
        return renderer.render(geometry, mask=mask, parallel=parallel)

    try:
        with one_blas_thread():
            reference = {p: call(shipped, p) for p in (True, False)}
            for arm in ("floats", "pairs"):
                same = all(np.array_equal(call(arms[arm], p), reference[p]) for p in (True, False))
                print(json.dumps({"arm": arm, "identical_to_shipped": same}), flush=True)
            out = np.empty((geometry.rows, geometry.cols), np.float32)
            for rnd in range(args.rounds):
                for arm, kernels in arms.items():
                    use(kernels)
                    record = {"round": rnd, "arm": arm}
                    for parallel, key in ((False, "serial"), (True, "parallel")):
                        times = []
                        for _ in range(args.calls + 2):
                            t0 = time.perf_counter()
                            renderer.render(geometry, mask=mask, out=out, parallel=parallel)
                            times.append((time.perf_counter() - t0) * 1e6)
                        times = times[2:]
                        record[f"{key}_us_min"] = round(min(times), 1)
                        record[f"{key}_us_median"] = round(float(np.median(times)), 1)
                    if "busy" in kernels:
                        lanes_ns, scalar_ns = kernels["busy"]()
                        record["busy_lanes_ns_per_sample"] = round(lanes_ns, 3)
                        record["shipped_pairs_ns_per_sample"] = round(scalar_ns, 3)
                    print(json.dumps(record), flush=True)
    finally:
        use(shipped)


if __name__ == "__main__":
    main()
