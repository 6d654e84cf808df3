"""The compiled constitutive update: every material's point law through one
cached kernel (any dimension).

For each particle i of a body (``index``, or every particle):

    A = I + dt L_i                          the step's deformation increment
    finite strain:  F_i <- A F_i,  V_i = V0_i det F_i
    small strain:   V_i <- V_i det A
    state_out_k <- state_k                  the state carried over ...
    stress_i, state_out_k <- law(params, L_i, F, dt, stress_i, state_k, ...)
                                            ... and updated by the law; F = F_i or A

``state`` and ``state_out`` (rows, n_state) hold the packed per-particle
state of the body's particles, row k for the k-th particle of the body (the
particle itself when ``every``); a material without state passes arrays of
n_state = 0 (nothing is copied). The law is a C callback of the signature
:data:`skfem_mpm.materials.compiled.POINT_SIGNATURE`, passed by its address
(so this kernel is compiled and cached once for all materials). Returns the first particle with
det <= 0 (-1 for none); the NumPy reference is each material's ``update``.

The current wave speed of a finite-strain material (the adaptive time
step): ``max_wave_speed`` is max_i c(params, F_i, m_i, V0_i, state_i) over
the particles, c the material's compiled point wave speed, a C callback of
the signature :data:`skfem_mpm.materials.compiled.WAVE_SPEED_SIGNATURE`
passed by its address (NaN when any particle's is NaN).
"""
import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic

__all__ = ["determinant", "material_update", "max_wave_speed"]


@intrinsic
def _call_law(typingctx, address, params, L, F, dim, dt, stress, state, stress_out, state_out):
    """Call the C callback at ``address`` (an integer: typing it costs
    nothing per call, unlike a function object) with the data pointers of
    the arrays (POINT_SIGNATURE)."""
    sig = types.void(address, params, L, F, dim, dt, stress, state, stress_out, state_out)

    def codegen(context, builder, signature, args):
        a_address, a_params, a_L, a_F, a_dim, a_dt, a_s, a_st, a_so, a_sto = args
        ty = signature.args
        double_p = ir.DoubleType().as_pointer()
        intp = context.get_value_type(types.intp)

        def data(i, value):
            return context.make_array(ty[i])(context, builder, value).data

        def length(i, value):
            return builder.extract_value(context.make_array(ty[i])(context, builder, value)
                                         .shape, 0)

        fnty = ir.FunctionType(ir.VoidType(), [double_p, intp, double_p, double_p, intp,
                                               ir.DoubleType(), double_p, double_p, intp,
                                               double_p, double_p])
        fn = builder.inttoptr(a_address, fnty.as_pointer())
        builder.call(fn, [data(1, a_params), length(1, a_params), data(2, a_L), data(3, a_F),
                          a_dim, a_dt, data(6, a_s), data(7, a_st), length(7, a_st),
                          data(8, a_so), data(9, a_sto)])
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, inline="always")
def determinant(A, dim):
    """det A of a dim x dim matrix, dim = 1, 2, 3 (3 x 3 by the rule of
    Sarrus, as :func:`skfem_mpm.materials.base.det`)."""
    if dim == 1:
        return A[0, 0]
    if dim == 2:
        return A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    return (A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
            - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
            + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]))


@njit(cache=True, parallel=True, error_model="numpy")
def material_update(law, params, index, every, L, dt, finite, stress, F, V, V0, state,
                    stress_out, F_out, V_out, state_out, first_bad):
    """See the module docstring; ``first_bad`` (threads,) receives each
    block's first particle with det <= 0 (or -1)."""
    n = L.shape[0] if every else index.shape[0]
    dim = L.shape[1]
    n_state = state.shape[1]
    nt = first_bad.shape[0]
    for t in prange(nt):
        A = np.empty((dim, dim))
        G = np.empty((dim, dim))
        bad = -1
        for k in range(t * n // nt, (t + 1) * n // nt):
            i = k if every else index[k]
            for c in range(n_state):
                state_out[k, c] = state[k, c]
            for a in range(dim):
                for b in range(dim):
                    A[a, b] = dt * L[i, a, b] + (1.0 if a == b else 0.0)
            if finite:
                for a in range(dim):
                    for b in range(dim):
                        s = 0.0
                        for c in range(dim):
                            s += A[a, c] * F[i, c, b]
                        F_out[i, a, b] = s
                        G[a, b] = s
                J = determinant(G, dim)
                V_out[i] = V0[i] * J
                _call_law(law, params, L[i], G, dim, dt, stress[i], state[k], stress_out[i],
                          state_out[k])
            else:
                J = determinant(A, dim)
                V_out[i] = V[i] * J
                _call_law(law, params, L[i], A, dim, dt, stress[i], state[k], stress_out[i],
                          state_out[k])
            if not J > 0.0 and bad < 0:
                bad = i
        first_bad[t] = bad


@intrinsic
def _call_wave_speed(typingctx, address, params, F, dim, m, V0, state):
    """The wave speed of the C callback at ``address`` (an integer) for one
    particle (WAVE_SPEED_SIGNATURE: the arrays' data pointers)."""
    sig = types.float64(address, params, F, dim, m, V0, state)

    def codegen(context, builder, signature, args):
        a_address, a_params, a_F, a_dim, a_m, a_V0, a_state = args
        ty = signature.args
        double_p = ir.DoubleType().as_pointer()
        intp = context.get_value_type(types.intp)

        def array(i, value):
            return context.make_array(ty[i])(context, builder, value)

        fnty = ir.FunctionType(ir.DoubleType(), [double_p, intp, double_p, intp,
                                                 ir.DoubleType(), ir.DoubleType(), double_p,
                                                 intp])
        fn = builder.inttoptr(a_address, fnty.as_pointer())
        params_, state_ = array(1, a_params), array(6, a_state)
        return builder.call(fn, [params_.data, builder.extract_value(params_.shape, 0),
                                 array(2, a_F).data, a_dim, a_m, a_V0, state_.data,
                                 builder.extract_value(state_.shape, 0)])

    return sig, codegen


@njit(cache=True, parallel=True, error_model="numpy")
def max_wave_speed(speed, params, F, m, V0, state, block_max):
    """max_i c_i of the callback ``speed`` over the particles (see the
    module docstring); ``block_max`` (threads,) receives each thread
    block's maximum (the maximum is exact: any blocks give the same)."""
    n = F.shape[0]
    dim = F.shape[1]
    nt = block_max.shape[0]
    for t in prange(nt):
        best = -np.inf
        for i in range(t * n // nt, (t + 1) * n // nt):
            c = _call_wave_speed(speed, params, F[i], dim, m[i], V0[i], state[i])
            if c > best or c != c:
                best = c
            if best != best:
                break
        block_max[t] = best
    top = -np.inf
    for t in range(nt):
        if block_max[t] > top or block_max[t] != block_max[t]:
            top = block_max[t]
        if top != top:
            break
    return top
