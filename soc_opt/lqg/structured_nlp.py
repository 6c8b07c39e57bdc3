"""The ``"structured"`` NLP formulation of the KL step (docs/math.md §6): rescaled single shooting with
analytic adjoint derivatives and a per-step block-diagonal Hessian (:class:`StructuredNLP`),
exposed to CasADi through buffer callbacks.  Solved by :func:`.casadi_nlp._casadi_structured`."""

from __future__ import annotations

import numpy as np

from ..models import symmetrize
from .moments import forward_arrays
from .problem import KLProblem


class StructuredNLP:
    """Scaled single-shooting NLP of the KL step with analytic first and second derivatives.

    Homogeneous state ``x = (s, 1)`` (``n1 = n + 1``), second moments ``X_k = E[x_k x_k^T]``,
    ``G_k = [K_k, k_k]``; ``X_{k+1} = Acl X_k Acl^T + Bt S_k Bt^T + Wt`` with
    ``Acl = [[A, c], [0, 1]] + Bt G``, ``Bt = [B; 0]``, ``Wt = blkdiag(W, 0)``;
    ``E[l_k] = 1/2 tr(Ct [I; G] X [I; G]^T) + 1/2 tr(Ct_uu S)`` (``Ct``: the cost in ``(s, 1, a)``).

    Variables (per unpinned step ``Z_k``, per free step also the lower-triangular ``Gam_k``)::

        G_k = Gh_k + Lh_k Z_k Mx_k,        L_k = Lh_k Gam_k   (Sigma_k = L_k L_k^T)

    where ``Sh = Lh Lh^T`` and ``Mx_k^T Mx_k = (X_k of the reference policy)^-1``, eigenvalues
    floored at 1e-6 of the largest (a singular ``X_k``, e.g. from ``P0 = 0``, leaves the NLP flat
    in some directions of ``K_k``; with a floor of 1e-8 the amplified roundoff there made IPOPT
    drift away after converging).  This affine change of variables is a preconditioner: the KL
    is ``1/2 (|Gam|_F^2 - m - 2 sum log Gam_ii + tr(Z Mx X Mx^T Z^T))``, with Hessian close to the
    identity; the reference is ``Z = 0, Gam = I``.  ``Gam_ii >= chol_floor``.

    Derivatives.  The Lagrangian ``sigma f + sum_k lam_k KL_k`` is linear in each ``X_k`` given
    the later policy: ``tr(Lam_k X_k) + const`` with the adjoint (value-function) recursion
    ``Q_k = sigma Ct_k + 2 F_k^T Lam_{k+1} F_k + lam_k H_k``, ``Lam_k = 1/2 [I; G]^T Q_k [I; G]``
    (``F_k = [[A, c, B], [0, 1, 0]]``, ``H_k`` the quadratic form of ``-log phat``).  Hence
    ``dL/dG_k = (Q_ux + Q_uu G) X_k`` and ``dL/dGam_k = tril(Lh^T Q_uu Lh Gam) - lam_k diag(1/Gam_ii)``.
    The per-step constraint Jacobian runs one such recursion per KL row, all rows at once
    (``O(T^2 n^3)`` flops in batched matrix products).  Hessian: the exact diagonal blocks
    ``(Mx X Mx^T) kron (Lh^T Q_uu Lh)`` (``Z``) and ``(Lh^T Q_uu Lh)_{ii'} delta_{jj'}
    + lam_k / Gam_ii^2`` (``Gam``; no ``Z``-``Gam`` coupling).  The off-diagonal blocks
    ``d2L/dtheta_j dtheta_k = (Q_ux + Q_uu G)_k dX_k/dtheta_j`` vanish at a KKT point (there
    ``(Q_ux + Q_uu G_k) X_k = 0`` with ``X_k`` positive definite: the backward-pass optimality), so
    IPOPT sees the exact Hessian at the solution and converges superlinearly, while the Hessian
    costs ``O(T (m n)^2)`` memory instead of the dense ``(T m n)^2``.

    Alternatives tried on the same rescaled single-shooting NLP: IPOPT's limited-memory BFGS
    Hessian with CasADi AD gradients needed 160 iterations at ``n=6, m=3, T=20`` and had not
    converged after 330 iterations (inf_pr ~ 5e2) at ``n=26, m=7, T=100`` (total budget); with
    per-step budgets, building the constraint Jacobian by CasADi AD through chained step
    functions took time quadratic in ``T`` (12 s at ``T=10``), because every KL row needs its own
    adjoint sweep.
    """

    def __init__(self, prob: KLProblem, kind: np.ndarray, scalar: bool, chol_floor: float):
        T, n, m = prob.T, prob.n, prob.m
        n1 = n + 1
        self.prob, self.T, self.n, self.m, self.n1 = prob, T, n, m, n1
        self.kind, self.scalar = kind, scalar
        self.free = kind == "free"
        self.var = kind != "pin"
        self.cons = np.flatnonzero(self.free)
        self.ng = (1 if scalar else self.cons.size) if self.cons.size else 0
        self.tl = np.tril_indices(m)
        self.nt = self.tl[0].size
        self.nz = m * n1
        self.sizes = np.where(self.free, self.nz + self.nt, np.where(self.var, self.nz, 0))
        self.off = np.concatenate([[0], np.cumsum(self.sizes)]).astype(int)
        self.nx = int(self.off[-1])
        ref = prob.reference
        self.Fx = np.ascontiguousarray(prob.F[:, :, :n1])
        self.Fu = np.ascontiguousarray(prob.F[:, :, n1:])
        self.Wt = np.zeros((T, n1, n1))
        self.Wt[:, :n, :n] = prob.dynamics.cov
        x0h = np.append(prob.mu0, 1.0)
        self.X0 = np.outer(x0h, x0h)
        self.X0[:n, :n] += prob.P0
        mg = forward_arrays(prob.dynamics, ref.K, ref.k, ref.cov, prob.mu0, prob.P0)
        xm = np.concatenate([mg.mean[:T], np.ones((T, 1))], axis=1)
        Xr = xm[:, :, None] * xm[:, None, :]
        Xr[:, :n, :n] += mg.cov[:T]
        w, V = np.linalg.eigh(symmetrize(Xr))
        w = np.maximum(w, 1e-6 * w[:, -1:])
        self.Mx = np.swapaxes(V / np.sqrt(w)[:, None, :], 1, 2)  # Mx Xr Mx^T ~ I
        self.Lh, self.Gh = prob.Lh, prob.Kth
        x0 = np.zeros(self.nx)
        lbx = np.full(self.nx, -np.inf)
        diag = self.tl[0] == self.tl[1]
        for t in self.cons:
            o = self.off[t] + self.nz
            x0[o : o + self.nt] = diag
            lbx[o : o + self.nt] = np.where(diag, chol_floor, -np.inf)
        self.x0, self.lbx = x0, lbx
        self._key, self._cache = None, None

    # -- moments --------------------------------------------------------------------------------

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T, m, n1 = self.T, self.m, self.n1
        Z = np.zeros((T, m, n1))
        Gam = np.zeros((T, m, m))
        for t in np.flatnonzero(self.var):
            o = self.off[t]
            Z[t] = x[o : o + self.nz].reshape(n1, m).T  # column-major, as CasADi's reshape
            if self.free[t]:
                Gam[t][self.tl] = x[o + self.nz : o + self.nz + self.nt]
        return Z, Gam

    def policy(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Z, Gam = self.unpack(x)
        G = self.Gh + self.Lh @ Z @ self.Mx
        LG = self.Lh @ Gam
        S = LG @ np.swapaxes(LG, 1, 2)
        pin = self.kind == "pin"
        S[pin] = self.prob.Sh[pin]
        return G, S, Gam

    def forward(self, x: np.ndarray) -> dict:
        key = x.tobytes()
        if key == self._key:
            return self._cache
        T, n1 = self.T, self.n1
        Z, _ = self.unpack(x)
        G, S, Gam = self.policy(x)
        Acl = self.Fx + self.Fu @ G
        N = self.Fu @ S @ np.swapaxes(self.Fu, 1, 2) + self.Wt
        X = np.empty((T, n1, n1))
        X[0] = self.X0
        for t in range(T - 1):
            Xn = Acl[t] @ X[t] @ Acl[t].T + N[t]
            X[t + 1] = 0.5 * (Xn + Xn.T)
        IG = np.concatenate([np.broadcast_to(np.eye(n1), (T, n1, n1)), G], axis=1)  # (T, n1 + m, n1)
        Y = self.Mx @ X @ np.swapaxes(self.Mx, 1, 2)
        c = {"Z": Z, "Gam": Gam, "G": G, "S": S, "Acl": Acl, "X": X, "IG": IG, "Y": Y}
        self._key, self._cache = key, c
        return c

    # -- derivatives ----------------------------------------------------------------------------

    def _adjoint(self, x: np.ndarray, sigma: float, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradient of ``sigma f + sum_k lam_k KL_k`` and the ``Q_uu`` of every step."""
        c = self.forward(x)
        T, m, n1, nz, nt = self.T, self.m, self.n1, self.nz, self.nt
        prob = self.prob
        grad = np.zeros(self.nx)
        Quu_all = np.empty((T, m, m))
        Lam = np.zeros((n1, n1))
        for t in range(T - 1, -1, -1):
            Ft = prob.F[t]
            Q = sigma * prob.Ct[t] + 2.0 * (Ft.T @ Lam @ Ft)
            if lam[t] != 0.0:
                Q = Q + lam[t] * prob.H[t]
            Quu = Q[n1:, n1:]
            Quu_all[t] = Quu
            if self.var[t]:
                o = self.off[t]
                gG = (Q[n1:, :n1] + Quu @ c["G"][t]) @ c["X"][t]
                grad[o : o + nz] = (self.Lh[t].T @ gG @ self.Mx[t].T).T.ravel()
                if self.free[t]:
                    Gm = c["Gam"][t]
                    gGam = self.Lh[t].T @ Quu @ self.Lh[t] @ Gm
                    gGam[np.diag_indices(m)] -= lam[t] / np.diag(Gm)
                    grad[o + nz : o + nz + nt] = gGam[self.tl]
            IG = c["IG"][t]
            Lam = 0.5 * (IG.T @ Q @ IG)
            Lam = 0.5 * (Lam + Lam.T)
        return grad, Quu_all

    def grad_f(self, x: np.ndarray) -> np.ndarray:
        return self._adjoint(x, 1.0, np.zeros(self.T))[0]

    def jac_g(self, x: np.ndarray) -> np.ndarray:
        """Dense ``(ng, nx)`` Jacobian of the KL rows (lower block triangular for per-step rows)."""
        if self.scalar:
            return self._adjoint(x, 0.0, self.free.astype(float))[0][None, :]
        c = self.forward(x)
        T, m, n1, nz, nt = self.T, self.m, self.n1, self.nz, self.nt
        J = np.zeros((self.ng, self.nx))
        stack = np.zeros((0, n1, n1))  # adjoints Lam^{(r)}_{t+1} of the rows r with cons[r] > t
        r_hi = self.ng  # those rows are r_hi..ng-1
        for t in range(T - 1, -1, -1):
            o = self.off[t]
            if self.var[t] and stack.shape[0]:
                Lh, Bt = self.Lh[t], self.Fu[t]
                W = np.swapaxes(stack @ (Bt @ Lh), 1, 2)  # Lh^T Bt^T Lam, (r, m, n1)
                gZ = W @ (2.0 * c["Acl"][t] @ c["X"][t] @ self.Mx[t].T)
                J[r_hi:, o : o + nz] = np.swapaxes(gZ, 1, 2).reshape(stack.shape[0], nz)
                if self.free[t]:
                    gGam = W @ (2.0 * Bt @ Lh @ c["Gam"][t])
                    J[r_hi:, o + nz : o + nz + nt] = gGam[:, self.tl[0], self.tl[1]]
            if self.free[t]:
                r = r_hi - 1
                Zt, Gm = c["Z"][t], c["Gam"][t]
                J[r, o : o + nz] = (Zt @ c["Y"][t]).T.ravel()
                gGam = Gm.copy()
                gGam[np.diag_indices(m)] -= 1.0 / np.diag(Gm)
                J[r, o + nz : o + nz + nt] = gGam[self.tl]
            if stack.shape[0]:
                Acl = c["Acl"][t]
                stack = np.swapaxes(stack @ Acl, 1, 2) @ Acl
                stack = 0.5 * (stack + np.swapaxes(stack, 1, 2))
            if self.free[t]:
                ZM = c["Z"][t] @ self.Mx[t]
                stack = np.concatenate([(0.5 * ZM.T @ ZM)[None], stack], axis=0)
                r_hi -= 1
        return J

    def hess_blocks(self, x: np.ndarray, sigma: float, lam_g: np.ndarray) -> list[np.ndarray]:
        """Diagonal blocks (one per unpinned step) of the Hessian of ``sigma f + lam_g^T g``."""
        lam = np.zeros(self.T)
        if self.ng:
            lam[self.cons] = lam_g[0] if self.scalar else lam_g
        c = self.forward(x)
        _, Quu = self._adjoint(x, sigma, lam)
        i, j = self.tl
        same_col = j[:, None] == j[None, :]
        dg = np.flatnonzero(i == j)
        blocks = []
        for t in np.flatnonzero(self.var):
            A = symmetrize(self.Lh[t].T @ Quu[t] @ self.Lh[t])
            hz = np.kron(c["Y"][t], A)
            if not self.free[t]:
                blocks.append(hz)
                continue
            hg = np.where(same_col, A[i[:, None], i[None, :]], 0.0)
            hg[dg, dg] += lam[t] / np.diag(c["Gam"][t]) ** 2
            B = np.zeros((self.sizes[t], self.sizes[t]))
            B[: self.nz, : self.nz] = hz
            B[self.nz :, self.nz :] = hg
            blocks.append(B)
        return blocks

    # -- CasADi ---------------------------------------------------------------------------------

    def oracle(self, ca):
        """``(x, f, g)`` as CasADi MX: one SX step function per step kind, chained over ``T``."""
        T, m, n1, nz, nt = self.T, self.m, self.n1, self.nz, self.nt
        d = n1 + m
        X = ca.SX.sym("X", n1, n1)
        zK, zL = ca.SX.sym("z", nz), ca.SX.sym("gam", nt)
        F, W, Ct = ca.SX.sym("F", n1, d), ca.SX.sym("W", n1, n1), ca.SX.sym("C", d, d)
        Gh, Lh, Mx = ca.SX.sym("Gh", m, n1), ca.SX.sym("Lh", m, m), ca.SX.sym("Mx", n1, n1)
        Zm = ca.reshape(zK, m, n1)
        ZM = ca.mtimes(Zm, Mx)
        IG = ca.vertcat(ca.SX.eye(n1), Gh + ca.mtimes(Lh, ZM))
        Acl = ca.mtimes(F, IG)
        Fu = F[:, n1:]
        XIG = ca.mtimes([IG, X, IG.T])

        def moments(S):
            Xn = ca.mtimes([Acl, X, Acl.T]) + ca.mtimes([Fu, S, Fu.T]) + W
            cost = 0.5 * (ca.sum1(ca.sum2(Ct * XIG)) + ca.sum1(ca.sum2(Ct[n1:, n1:] * S)))
            return Xn, cost

        Gam = ca.SX.zeros(m, m)
        for idx, (a, b) in enumerate(zip(*self.tl)):
            Gam[a, b] = zL[idx]
        LG = ca.mtimes(Lh, Gam)
        Xn, cost = moments(ca.mtimes(LG, LG.T))
        kl = 0.5 * (ca.sum1(ca.sum2(Gam * Gam)) - m - 2 * sum(ca.log(Gam[a, a]) for a in range(m))
                    + ca.sum1(ca.sum2(ca.mtimes(ZM, X) * ZM)))
        data = [F, W, Ct, Gh, Lh, Mx]
        f_free = ca.Function("kl_step_free", [X, zK, zL, *data], [Xn, cost, kl])
        f_det = ca.Function("kl_step_det", [X, zK, *data], list(moments(ca.SX.zeros(m, m))))
        x = ca.MX.sym("x", self.nx)
        Xc = ca.MX(self.X0)
        obj, kls = 0, []
        eye_tri = ca.DM(np.eye(m)[self.tl])
        zero = ca.DM.zeros(nz)
        prob = self.prob
        for t in range(T):
            dt = [prob.F[t], self.Wt[t], prob.Ct[t], self.Gh[t], self.Lh[t], self.Mx[t]]
            o = int(self.off[t])
            if self.kind[t] == "det":
                Xc, ct = f_det(Xc, x[o : o + nz], *dt)
            elif self.kind[t] == "free":
                Xc, ct, klt = f_free(Xc, x[o : o + nz], x[o + nz : o + nz + nt], *dt)
                kls.append(klt)
            else:  # pinned: Z = 0, Gam = I is the reference
                Xc, ct, _ = f_free(Xc, zero, eye_tri, *dt)
            obj = obj + ct
        g = ca.MX(0, 1) if not kls else (sum(kls) if self.scalar else ca.vertcat(*kls))
        return x, obj, g

    def derivative_functions(self, ca):
        """CasADi callbacks ``grad_f``, ``jac_g`` and ``hess_lag`` (``nlpsol`` signatures)."""
        nx, ng = self.nx, self.ng
        spx, spp, sp1, spg = (ca.Sparsity.dense(nx, 1), ca.Sparsity(0, 1), ca.Sparsity.dense(1, 1),
                              ca.Sparsity.dense(ng, 1))
        # Jacobian (compressed columns): the columns of step t hold the rows r with cons[r] >= t
        first = np.searchsorted(self.cons, np.arange(self.T)) if not self.scalar else np.zeros(self.T, int)
        colind = np.concatenate([[0], np.cumsum(np.repeat(ng - first, self.sizes))]).astype(int)
        rows = np.concatenate([np.tile(np.arange(first[t], ng), int(self.sizes[t])) for t in range(self.T)])
        jsp = ca.Sparsity(ng, nx, colind.tolist(), rows.astype(int).tolist())
        jseg = [(int(self.off[t]), int(self.sizes[t]), int(first[t]), int(colind[self.off[t]]))
                for t in range(self.T) if self.sizes[t]]
        # Hessian: upper triangle of the block diagonal, compressed columns
        tri = {nb: np.tril_indices(nb) for nb in set(self.sizes[self.var].tolist())}  # (col, row), by column
        steps = np.flatnonzero(self.var)
        hrow = np.concatenate([self.off[t] + tri[self.sizes[t]][1] for t in steps])
        per_col = np.concatenate([np.arange(1, self.sizes[t] + 1) for t in steps])  # column c of a block: c + 1
        hsp = ca.Sparsity(nx, nx, np.concatenate([[0], np.cumsum(per_col)]).astype(int).tolist(),
                          hrow.astype(int).tolist())
        hseg, pos = [], 0
        for t in np.flatnonzero(self.var):
            nb = int(self.sizes[t])
            hseg.append((pos, nb))
            pos += tri[nb][0].size

        def grad_f(arg, res):
            x = arg[0]
            if res[0] is not None and res[0].size:
                res[0][0] = self._cost(x)
            if res[1] is not None:
                res[1][:] = self.grad_f(x)

        def jac_g(arg, res):
            x = arg[0]
            if res[0] is not None and res[0].size:
                res[0][:] = self.constraints(x)
            out = res[1]
            if out is None:
                return
            J = self.jac_g(x)
            for o, nb, r0, pos in jseg:
                blk = J[r0:, o : o + nb].T.ravel()
                out[pos : pos + blk.size] = blk

        def hess(arg, res):
            blocks = self.hess_blocks(arg[0], float(arg[2][0]), arg[3])
            out = res[0]
            for (pos, nb), B in zip(hseg, blocks):
                c_, r_ = tri[nb]
                out[pos : pos + c_.size] = B[r_, c_]

        return (_buffer_callback(ca, "kl_step_grad_f", [spx, spp], [sp1, spx], grad_f),
                _buffer_callback(ca, "kl_step_jac_g", [spx, spp], [spg, jsp], jac_g),
                _buffer_callback(ca, "kl_step_hess_l", [spx, spp, sp1, spg], [hsp], hess))

    def _cost(self, x: np.ndarray) -> float:
        """``f = sum_k E[l_k]`` (the oracle's objective, in NumPy)."""
        c = self.forward(x)
        XIG = c["IG"] @ c["X"] @ np.swapaxes(c["IG"], 1, 2)
        Ct, n1 = self.prob.Ct, self.n1
        return float(0.5 * (np.einsum("tij,tij->", Ct, XIG) + np.einsum("tij,tij->", Ct[:, n1:, n1:], c["S"])))

    def constraints(self, x: np.ndarray) -> np.ndarray:
        """The KL rows ``g`` (the oracle's constraints, in NumPy)."""
        c = self.forward(x)
        fr = self.free
        Gam = c["Gam"][fr]
        kl = 0.5 * ((Gam**2).sum(axis=(1, 2)) - self.m - 2.0 * np.log(np.diagonal(Gam, axis1=1, axis2=2)).sum(axis=1)
                    + np.einsum("tij,tjk,tik->t", c["Z"][fr], c["Y"][fr], c["Z"][fr]))
        return np.array([kl.sum()]) if self.scalar else kl


def _buffer_callback(ca, name: str, sp_in: list, sp_out: list, fn):
    """A CasADi ``Callback`` evaluating ``fn(inputs, outputs)`` on NumPy views of its buffers."""

    class _Callback(ca.Callback):
        def __init__(self):
            ca.Callback.__init__(self)
            self.construct(name, {})

        def get_n_in(self):
            return len(sp_in)

        def get_n_out(self):
            return len(sp_out)

        def get_sparsity_in(self, i):
            return sp_in[i]

        def get_sparsity_out(self, i):
            return sp_out[i]

        def has_eval_buffer(self):
            return True

        def eval_buffer(self, arg, res):
            view = lambda b: None if b is None else np.frombuffer(b, dtype=float)  # noqa: E731
            fn([view(a) for a in arg], [view(r) for r in res])
            return 0

    return _Callback()
