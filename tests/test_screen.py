"""The score screen's Gauss-Newton start on a linear model, where every step is exact."""

from __future__ import annotations

import types

import numpy as np
import pytest

from brain_fe.parameters import Param
from diagnosis.effects import Effect
from diagnosis.screen import MAX_STEP_OF_RANGE, score

MU, EFF = Param("mu", 0), Param("beta", 0)


_Effect = Effect("linear", ("beta_0",), (0.0,), (1.0,), ({"beta_0": 0.0},), "", "",
                 neutral={"beta_0": 0.0})


def _problem(effect_size: float):
    """y = mu * a + beta * b with a, b partly aligned; data at mu = 2, beta = effect_size."""
    x = np.linspace(0.0, 1.0, 40)
    a, b = x, x**2
    data = 2.0 * a + effect_size * b

    def predict(values, names):
        y = values[MU] * a + values[EFF] * b
        cols = {MU: a, EFF: b}
        jac = np.column_stack([cols[n] for n in names]) if names else np.zeros((x.size, 0))
        return types.SimpleNamespace(y=y, jacobian=jac)

    sim = types.SimpleNamespace(predict=predict, nu0=0.49)
    obs = {"value": data}
    current = types.SimpleNamespace(values={MU: 1.0, EFF: 0.0},
                                    prediction=predict({MU: 1.0, EFF: 0.0}, []).y)
    return sim, obs, a, b, current


class _Obs(dict):
    def __getitem__(self, k):
        return types.SimpleNamespace(to_numpy=lambda dtype=None: dict.__getitem__(self, k))


def test_score_start_takes_the_joint_step_when_it_is_short():
    sim, obs, a, _, current = _problem(0.2)
    s = score(sim, _Obs(obs), np.ones(40), current, _Effect, {"beta_0": 0.0}, [MU],
              a[:, None])
    # a linear model: one Gauss-Newton step lands on the truth (1e-10)
    assert abs(s.start[MU] - 2.0) < 1e-10 and abs(s.start[EFF] - 0.2) < 1e-10
    assert s.dof == 1 and s.lm > 0


def test_score_start_holds_a_long_step_and_solves_the_base_without_it():
    size = 3.0 / MAX_STEP_OF_RANGE  # ten times the trusted share of the range
    sim, obs, a, b, current = _problem(size)
    s = score(sim, _Obs(obs), np.ones(40), current, _Effect, {"beta_0": 0.0}, [MU],
              a[:, None])
    assert s.start[EFF] == 0.0  # held at the design point
    # mu takes the least-squares step of the base alone, not the joint one (mu = 2)
    mu_alone = float(np.linalg.lstsq(a[:, None], obs["value"], rcond=None)[0][0])
    assert abs(s.start[MU] - mu_alone) < 1e-10 and abs(mu_alone - 2.0) > 1.0


def test_score_at_a_point_of_finite_size_predicts_once_and_scores_the_same():
    """At a design point away from the neutral one (beta = 0.5 on y = mu a + beta b +
    mu beta a b, whose Jacobian there is not the base one) the score asks for the point's
    whole Jacobian in one prediction; the statistic and the start are exactly those of the
    two predictions (the effect's columns, then all) made where the neutral is unknown."""
    x = np.linspace(0.0, 1.0, 40)
    a, b = x, x**2
    data = 2.0 * a + 0.3 * b + 0.6 * a * b
    calls = []

    def predict(values, names):
        calls.append(list(names))
        mu, beta = values[MU], values[EFF]
        cols = {MU: a + beta * a * b, EFF: b + mu * a * b}
        jac = np.column_stack([cols[n] for n in names]) if names else np.zeros((x.size, 0))
        return types.SimpleNamespace(y=mu * a + beta * b + mu * beta * a * b, jacobian=jac)

    sim = types.SimpleNamespace(predict=predict, nu0=0.49)
    current = types.SimpleNamespace(values={MU: 1.0, EFF: 0.0},
                                    prediction=predict({MU: 1.0, EFF: 0.0}, []).y)
    unknown = Effect("linear", ("beta_0",), (0.0,), (1.0,), ({"beta_0": 0.0},), "", "")
    out = []
    for eff in (_Effect, unknown):
        calls.clear()
        out.append((score(sim, _Obs({"value": data}), np.ones(40), current, eff,
                          {"beta_0": 0.5}, [MU], a[:, None]), list(calls)))
    (own, once), (two, twice) = out
    assert once == [[MU, EFF]] and twice == [[EFF], [MU, EFF]]
    assert own.lm == two.lm > 0 and own.start == two.start and own.dof == two.dof == 1
    # at the neutral point both ask for the effect's column alone, and score alike
    calls.clear()
    neutral = score(sim, _Obs({"value": data}), np.ones(40), current, _Effect,
                    {"beta_0": 0.0}, [MU], (a + 0.0)[:, None])
    assert calls == [[EFF]] and neutral.lm > 0


def test_effects_state_where_they_are_the_base_model():
    """Every library effect states its neutral values; a design point is of finite size
    exactly when it sets one of them elsewhere (nu0: the assumed value)."""
    from diagnosis.effects import EFFECTS, GLUED_ENDS, HOMOGENEOUS_ARTEFACTS

    for e in (*EFFECTS.values(), GLUED_ENDS, HOMOGENEOUS_ARTEFACTS):
        assert e.neutral and set(e.neutral) <= set(e.names), e.name
    ve, nu, glue = EFFECTS["viscoelastic"], EFFECTS["compressibility"], EFFECTS[
        "imperfect_gluing"]
    assert not ve.of_finite_size({"beta_0": 0.0, "log10_tau_0": 1.0}, 0.49)
    assert ve.of_finite_size({"beta_0": 0.1, "log10_tau_0": 1.0}, 0.49)
    assert not nu.of_finite_size({"nu0": 0.49}, 0.49) and nu.of_finite_size({"nu0": 0.4}, 0.49)
    assert glue.of_finite_size({"log10_k": 4.0}, 0.49)  # neutral only at infinite stiffness


def test_second_start_only_for_a_held_best_point():
    from diagnosis.screen import Score
    from diagnosis.selection import second_start

    held = Score("g", 100.0, 1, {}, {"log10_k": 2.0}, held=("log10_k",))
    near = Score("g", 60.0, 1, {}, {"log10_k": 0.2})
    weak = Score("g", 1.0, 1, {}, {"log10_k": -1.0})
    other = Score("h", 90.0, 1, {}, {})
    assert second_start([held, near, weak, other, None], held, needed=20.0) is near
    assert second_start([held, weak], held, needed=20.0) is None  # cannot earn a place
    far = Score("g", 80.0, 1, {}, {"log10_k": 1.0}, held=("log10_k",))
    assert second_start([held, far, weak], held, needed=20.0) is far  # held, but the next
    assert second_start([held, far, near], held, needed=20.0) is near  # trusted first
    assert second_start([near, weak], near, needed=20.0) is None  # the best was trusted


def test_detection_limit_is_the_step_that_earns_a_place():
    """On a linear model y = mu a + nu0 b + offsets, the stated detection limit of nu0
    beside the current model (mu, and a second parameter with a zero column: it must not
    project anything out) is the step s whose signature s b, refitted with mu by least
    squares, removes exactly the bar (here 16) of chi-square.  A force offset whose column
    is a multiple of a is masked by the model (alone it would show); a torque offset with
    no signature at all is not masked, merely invisible; a NaN Jacobian is refused."""
    import pytest

    from diagnosis.effects import EFFECTS
    from diagnosis.screen import detection_limits, masked_by_model

    x = np.linspace(0.0, 1.0, 50)
    a, b = x, x**2
    N0, FO, TO = Param("nu0"), Param("force_offset"), Param("torque_offset")
    cols = {MU: a, N0: b, FO: 3.0 * a, Param("stretch_offset"): np.ones_like(x),
            TO: np.zeros_like(x)}

    def predict(values, names):
        return types.SimpleNamespace(y=None, jacobian=np.column_stack([cols[n] for n in names]))

    sim = types.SimpleNamespace(nu0=0.49, predict=predict)
    current = types.SimpleNamespace(values={MU: 2.0})
    sd = 0.01
    effects = {e: EFFECTS[e] for e in ("compressibility", "artefacts")}
    J = np.column_stack([a, np.zeros_like(x)])
    limits = detection_limits(sim, current, [MU, Param("mu_1")], J, effects,
                              lambda J: J / sd, lambda eff: 16.0)
    nu = limits["compressibility"]["nu0"]
    data = 2.0 * a + nu["step"] * b  # nu0 short of 0.49 by the step, refitted with mu
    (m,), *_ = np.linalg.lstsq(a[:, None], data, rcond=None)
    assert abs(np.sum(((data - m * a) / sd) ** 2) - 16.0) < 1e-6
    assert nu["would_show_at"] == [0.49 - nu["step"]] and nu["within_bounds"]
    art = limits["artefacts"]
    assert not art["force_offset"]["within_bounds"]
    assert masked_by_model(art["force_offset"], EFFECTS["artefacts"].bounds(FO))
    assert not art["torque_offset"]["within_bounds"]
    assert not masked_by_model(art["torque_offset"], EFFECTS["artefacts"].bounds(TO))
    assert art["stretch_offset"]["within_bounds"]
    with pytest.raises(ValueError, match="not finite"):
        detection_limits(sim, current, [MU], np.full((50, 1), np.nan), effects,
                         lambda J: J / sd, lambda eff: 16.0)


def test_a_candidate_hidden_behind_a_named_effect():
    """y = mu a + k g + nu0 b on a linear model, g (a named glue layer's column) nearly
    along b: beside mu alone nu0 would show at the step whose signature, refitted with mu,
    removes the bar (16); beside mu and g its step is longer by the factor of the textbook
    collinearity, 1 / sqrt(1 - R^2) with R^2 of b on g after mu, and the candidate is
    reported hidden behind the glue layer (variance inflation >= 10) with its separating
    test; a g orthogonal to b hides nothing."""
    from diagnosis.effects import EFFECTS
    from diagnosis.screen import HIDDEN_INFLATION, detection_limits, hidden_behind

    x = np.linspace(0.0, 1.0, 50)
    a, b = x, x**2
    K = Param("log10_k")
    sd = 0.01
    lib = {"compressibility": EFFECTS["compressibility"]}

    def limits_with(g):
        cols = {MU: a, Param("nu0"): b, K: g}
        sim = types.SimpleNamespace(nu0=0.49, predict=lambda values, names: types.
                                    SimpleNamespace(y=None, jacobian=np.column_stack(
                                        [cols[n] for n in names])))
        return detection_limits(sim, types.SimpleNamespace(values={MU: 2.0, K: 1.0}),
                                [MU, K], np.column_stack([a, g]), lib, lambda J: J / sd,
                                lambda eff: 16.0, named={"imperfect_gluing": (K,)})

    def residual(col, *others):  # of col after least squares on the others
        A = np.column_stack(others)
        return col - A @ np.linalg.lstsq(A, col, rcond=None)[0]

    g = b + 0.01 * np.sin(9.0 * x)  # nearly b
    nu = limits_with(g)["compressibility"]["nu0"]
    s0 = nu["step_without"]["imperfect_gluing"]
    data = 2.0 * a + s0 * b  # nu0 short of 0.49 by the step without g, refitted with mu
    (m,), *_ = np.linalg.lstsq(a[:, None], data, rcond=None)
    assert abs(np.sum(((data - m * a) / sd) ** 2) - 16.0) < 1e-6
    rb = residual(b, a)
    r2 = 1.0 - np.sum(residual(b, a, g) ** 2) / np.sum(rb**2)
    assert abs((nu["step"] / s0) ** 2 - 1.0 / (1.0 - r2)) < 1e-6 * (1.0 / (1.0 - r2))
    (h,) = hidden_behind({"compressibility": {"nu0": nu}}, lib)
    assert h["effect"] == "compressibility" and h["behind"] == "imperfect_gluing"
    assert h["inflation"] >= HIDDEN_INFLATION and h["would_show_without"] == [0.49 - s0]
    assert "lubricated" in h["separating_test"]
    # a glue column orthogonal to b after mu changes nothing: nothing hidden
    g_orth = residual(np.sin(3.0 * np.pi * x), a, b)
    nu = limits_with(g_orth)["compressibility"]["nu0"]
    assert abs(nu["step"] / nu["step_without"]["imperfect_gluing"] - 1.0) < 1e-9
    assert hidden_behind({"compressibility": {"nu0": nu}}, lib) == []


def test_detection_limits_of_effects_with_a_time_or_exponent_of_their_own():
    """Viscoelasticity and a second Ogden term act at their neutral zero only through tau
    and alpha_1: their limit is stated at each design point, each a further Maxwell branch
    or Ogden term of zero size on a free index (the current model's two Ogden terms take
    mu_0 and mu_1, so the copies start at mu_2), all in one prediction, which also gives
    the model's own columns (on the path the further terms take).  On a linear model
    whose columns depend on the held tau or alpha, every stated step is the one whose
    signature, refitted with mu_0 by least squares, removes exactly the bar (16)."""
    from diagnosis.effects import EFFECTS
    from diagnosis.screen import detection_limits

    x = np.linspace(0.0, 1.0, 60)
    seen = {}

    def column(q, values):
        if q == MU:
            return x
        if q.family == "beta":
            return 1.0 - np.exp(-x / 10.0 ** values[Param("log10_tau", q.index)])
        return x ** (2.0 + values[Param("alpha", q.index)] / 10.0)  # mu_k

    def predict(values, names):
        seen.update({str(n): values[n] for n in names})
        seen["calls"] = seen.get("calls", 0) + 1
        return types.SimpleNamespace(y=None, jacobian=np.column_stack(
            [column(n, values) for n in names]))

    sim = types.SimpleNamespace(nu0=0.49, predict=predict)
    current = types.SimpleNamespace(values={MU: 1.0, Param("alpha", 0): -10.0,
                                            Param("mu", 1): 0.2, Param("alpha", 1): 5.0})
    effects = {e: EFFECTS[e] for e in ("viscoelastic", "ogden_2term")}
    points = {"viscoelastic": [{"beta_0": 0.0, "log10_tau_0": t} for t in (-1.0, 0.0)],
              "ogden_2term": [{"mu_1": 0.0, "alpha_1": a} for a in (-5.0, 5.0)]}
    sd = 0.01
    # the current model's own second Ogden term: the candidate ogden_2term is in the model
    limits = detection_limits(sim, current, [MU, Param("mu", 1)], x[:, None], effects,
                              lambda J: J / sd, lambda eff: 16.0, points)
    assert set(limits) == {"viscoelastic"}
    current.values = {MU: 1.0, Param("alpha", 0): -10.0}
    current.values[Param("mu", 1)] = 0.0  # a term of zero size does not free its index
    seen.clear()
    limits = detection_limits(sim, current, [MU], x[:, None], effects, lambda J: J / sd,
                              lambda eff: 16.0, points)
    # free indices, one solve, the model's own column from it too
    assert seen.pop("calls") == 1
    assert set(seen) == {"mu_0", "beta_0", "beta_1", "mu_2", "mu_3"}
    for e, held in (("viscoelastic", "log10_tau_0"), ("ogden_2term", "alpha_1")):
        assert len(limits[e]) == 2
        for v in limits[e].values():
            assert v["parameter"] == EFFECTS[e].names[0].__str__() and v["from"] == 0.0
            k = {"log10_tau_0": Param("log10_tau", 9), "alpha_1": Param("alpha", 9)}[held]
            q = Param("beta" if e == "viscoelastic" else "mu", 9)
            sig = v["step"] * column(q, {k: v["at"][held]})
            (m,), *_ = np.linalg.lstsq(x[:, None], x + sig, rcond=None)
            assert abs(np.sum(((x + sig - m * x) / sd) ** 2) - 16.0) < 1e-6
            assert v["would_show_at"] == [v["step"]]  # beta and mu_1 >= 0 only
    assert len({v["step"] for v in limits["viscoelastic"].values()}) == 2  # tau matters


def test_a_softening_is_stated_at_each_design_point_in_a_solve_of_its_own():
    """A softening (Mullins) acts at d = 0 only through its energy scale m, like tau and
    alpha_1, but a model holds one softening, so no free index takes further copies: one
    prediction per design point.  With d = 0 the path is the final fit's, so only d's
    column is predicted and the final fit's Jacobian serves for the model; where the
    prediction leaves that path by more than SAME_PATH_SD noise SDs (an elastic model's
    load steps change once a history is switched on) the model's columns come from the same
    prediction; closer, the final fit's still serve.  On a linear model
    whose softening column depends on m, every stated d is the one whose signature,
    refitted with mu by least squares, removes exactly the bar (16)."""
    from diagnosis.effects import EFFECTS
    from diagnosis.screen import PER_POINT, SAME_PATH_SD, detection_limits

    assert "mullins" in PER_POINT
    x = np.linspace(0.0, 1.0, 60)
    D, M = Param("softening"), Param("log10_softening_m")
    sd = 0.01
    points = {"mullins": [{"softening": 0.0, "log10_softening_m": v} for v in (-3.0, -1.0)]}
    # the path the softening puts the model on: the same, 0.2 SAME_PATH_SD off, 20 SD off
    for shift, path_moves in ((0.0, False), (0.1 * SAME_PATH_SD * sd, False), (0.1, True)):
        calls = []

        def predict(values, names, shift=shift, calls=calls):
            calls.append([str(q) for q in names])
            mu_col = x * (1.0 + shift if M in values else 1.0)
            d_col = -np.tanh(x / 10.0 ** (values[M] + 2.0)) * x  # d sigma / d d at d = 0
            cols = {MU: mu_col, D: d_col}
            return types.SimpleNamespace(
                y=values[MU] * mu_col + values.get(D, 0.0) * d_col,
                jacobian=np.column_stack([cols[q] for q in names]))

        sim = types.SimpleNamespace(nu0=0.49, predict=predict)
        current = types.SimpleNamespace(values={MU: 2.0}, prediction=2.0 * x)
        limits = detection_limits(sim, current, [MU], x[:, None],
                                  {"mullins": EFFECTS["mullins"]}, lambda J: J / sd,
                                  lambda eff: 16.0, points)["mullins"]
        own = [["softening"], ["mu_0", "softening"]] if path_moves else [["softening"]]
        assert calls == own * 2  # one prediction per design point (and the model's columns)
        assert len(limits) == 2 and len({v["step"] for v in limits.values()}) == 2
        for v in limits.values():
            assert v["parameter"] == "softening" and v["from"] == 0.0
            m = v["at"]["log10_softening_m"]
            mu_col = x * (1.0 + shift if path_moves else 1.0)  # the columns used
            sig = v["step"] * -np.tanh(x / 10.0 ** (m + 2.0)) * x
            (c,), *_ = np.linalg.lstsq(mu_col[:, None], sig, rcond=None)
            assert np.sum(((sig - c * mu_col) / sd) ** 2) == pytest.approx(16.0, rel=1e-9)
            assert v["would_show_at"] == [v["step"]]  # d >= 0 only
            assert v["step_alone"] == pytest.approx(4.0 / np.linalg.norm(sig / v["step"] / sd))


def test_a_glue_layer_is_stated_where_its_solved_misfit_reaches_the_bar():
    """Imperfect gluing vanishes at its neutral point (k -> infinity), and its signature is
    not linear in the compliance c = 1/k there (on the FE model its chi-square grows about
    as c: BENCHMARKS.md), so it is stated from direct solves.  On a model y = mu a +
    sqrt(c) g (g partly along a: mu mimics part of it), the stated log10 k is the one whose
    signature, refitted with mu by least squares, removes exactly the bar (16): a solve
    with its sensitivity at the design's stiffest point, one more at the Newton estimate
    (a power law: exact).  A layer the model can mimic entirely (g along a) is masked:
    alone an allowed glue would show."""
    from diagnosis.effects import EFFECTS
    from diagnosis.screen import detection_limits, masked_by_model

    x = np.linspace(0.0, 1.0, 50)
    a = x
    K = Param("log10_k")
    sd = 0.01
    glue = {"imperfect_gluing": EFFECTS["imperfect_gluing"]}
    points = {"imperfect_gluing": [{"log10_k": v} for v in (3.0, 1.5, 0.0)]}
    lo, hi = EFFECTS["imperfect_gluing"].bounds(K)
    for g, masked in ((x**2 + 0.3 * x, False), (-0.5 * x, True)):
        seen = []

        def predict(values, names=(), g=g, seen=seen):
            seen.append(values.get(K))
            c = 10.0 ** -values[K] if K in values else 0.0
            d = {MU: a, K: -0.5 * np.log(10.0) * np.sqrt(c) * g}  # d sqrt(c) / d log10_k
            return types.SimpleNamespace(y=values[MU] * a + np.sqrt(c) * g,
                                         jacobian=np.column_stack([d[q] for q in names])
                                         if names else None)

        sim = types.SimpleNamespace(nu0=0.49, predict=predict)
        current = types.SimpleNamespace(values={MU: 2.0}, prediction=predict({MU: 2.0}).y)
        seen.clear()
        v = detection_limits(sim, current, [MU], a[:, None], glue, lambda J: J / sd,
                             lambda eff: 16.0, points)["imperfect_gluing"]["log10_k"]
        assert v["from"] == hi and v["parameter"] == "log10_k"
        assert seen[0] == 3.0 and v["solved_at"] == sorted(set(seen))
        assert masked_by_model(v, (lo, hi)) is masked
        alone = 10.0 ** -(hi - v["step_alone"])  # beside nothing
        assert np.sum((np.sqrt(alone) * g / sd) ** 2) == pytest.approx(16.0, rel=1e-9)
        if masked:  # "no allowed value" only after solving the softest allowed glue
            assert v["would_show_at"] == [] and not v["within_bounds"]
            assert lo in v["solved_at"]
            continue
        assert len(seen) == 2  # a power law: one Newton step is exact
        (k_shows,) = v["would_show_at"]
        assert v["step"] == pytest.approx(hi - k_shows)
        data = 2.0 * a + np.sqrt(10.0 ** -k_shows) * g  # a glue that stiff, refitted with mu
        (m,), *_ = np.linalg.lstsq(a[:, None], data, rcond=None)
        assert np.sum(((data - m * a) / sd) ** 2) == pytest.approx(16.0, rel=1e-9)


def test_compressibility_is_told_apart_by_the_lateral_expansion():
    """Compressibility masked by any other effect: the separating test named is the lateral
    expansion, the one quantity only compressibility changes; a pair of the table keeps its
    own (gluing: a lubricated compression), a pair without compressibility the generic one."""
    from diagnosis.effects import LATERAL, separating_test

    assert separating_test("compressibility", "artefacts") == LATERAL
    assert separating_test("viscoelastic", "compressibility") == LATERAL
    assert "lubricated" in separating_test("imperfect_gluing", "compressibility")
    assert "different rate" in separating_test("mullins", "artefacts")


def test_limits_survive_a_history_that_cannot_be_followed(caplog):
    """engine._limits: compressibility and the offsets first (the fit's Jacobian), then the
    effects with design points in their own solve, then a glue layer in solves of its own;
    when the Maxwell branches' history cannot be followed the elastic second Ogden term is
    still stated, the failure logged, the diagnosis not failed; when the final path itself
    fails, nothing is stated (the groups are independent solves, shared among ranks)."""
    import logging

    import pandas as pd

    from diagnosis.effects import EFFECTS
    from diagnosis.engine import _limits
    from diagnosis.selection import Context
    from diagnosis.sharing import share_with

    n = 40
    x = np.linspace(0.0, 1.0, n)
    obs = pd.DataFrame({"specimen": "s", "curve": "torsion_0.15", "test": "torsion",
                        "amplitude": 0.15, "channel": "torque",
                        "branch": np.where(np.arange(n) < n // 2, "loading", "unloading"),
                        "cycle": 1, "control": 0.15 * np.sin(np.pi * x), "time_s": 30 * x,
                        "value": 0.0})
    calls = []

    K = Param("log10_k")

    def predict(values, names, fail=None):
        calls.append([str(q) for q in names])
        if fail is not None and fail(names):
            raise RuntimeError("Newton failed")
        glue = np.sqrt(10.0 ** -values[K]) * x**3 if K in values else np.zeros(n)
        return types.SimpleNamespace(y=glue, jacobian=np.column_stack(
            [-0.5 * np.log(10.0) * glue if q == K else x ** (1.0 + 0.1 * k)
             for k, q in enumerate(names)]))

    lib = {e: EFFECTS[e] for e in ("compressibility", "artefacts", "viscoelastic",
                                   "ogden_2term", "mullins", "imperfect_gluing")}
    current = types.SimpleNamespace(values={MU: 1.0, Param("alpha", 0): -10.0},
                                    prediction=np.zeros(n))
    nm = types.SimpleNamespace(whiten_jacobian=lambda J: J / 0.01, nu_level=lambda: np.inf)

    def run(fail):
        sim = types.SimpleNamespace(nu0=0.49, predict=lambda v, q: predict(v, q, fail))
        ctx = Context(sim, obs, np.ones(n), lib, [MU], 1e-3, 10.0, 40, share_with(None))
        calls.clear()
        return _limits(ctx, None, current, [], [], x[:, None], nm, None)

    with caplog.at_level(logging.WARNING, logger="diagnosis.engine"):
        limits, masked, hidden = run(lambda q: any(p.family == "beta" for p in q))
    assert set(limits) == {"compressibility", "artefacts", "ogden_2term", "mullins",
                           "imperfect_gluing"}
    assert len(limits["ogden_2term"]) == 4
    assert len(limits["mullins"]) == 3  # a solve per design point, in the design's order
    ms = [v["at"]["log10_softening_m"] for v in limits["mullins"].values()]
    assert ms == sorted(ms)
    glue = limits["imperfect_gluing"]["log10_k"]  # in its own solves (interface springs)
    assert len(calls) == 3 + 3 + len(glue["solved_at"]) and glue["within_bounds"]
    assert "Newton failed" in caplog.text
    limits, masked, hidden = run(lambda q: True)  # the final path itself
    assert limits == {} and masked == [] and hidden == []


def test_the_report_states_the_limits_and_what_is_masked():
    """report.md's limits: one row per stated parameter, 'no allowed value' where none
    would show, a line naming the glue stiffness below which a layer would show, and the
    masked candidates with the test that would tell."""
    from diagnosis.report import _limit_lines

    res = {"masked": [{"effect": "imperfect_gluing", "beside": ["artefacts"],
                       "separating_test": "a re-zeroed repeat test"}],
           "detection_limits": {
               "compressibility": {"nu0": {"from": 0.49, "would_show_at": [0.401]}},
               "imperfect_gluing": {"log10_k": {"from": 4.0, "would_show_at": [1.0],
                                                "solved_at": [1.0, 1.1, 2.07]}},
               "ogden_2term": {"mu_1 at alpha_1 = 5": {"from": 0.0, "would_show_at": []}}}}
    text = "\n".join(_limit_lines(res))
    assert "**Cannot tell whether imperfect_gluing is also present**: beside artefacts" in text
    assert "| compressibility | nu0 | 0.49 | 0.401 |" in text
    assert "| ogden_2term | mu_1 at alpha_1 = 5 | 0 | no allowed value |" in text
    assert "a glue layer softer than k = 10 kPa/mm would show" in text
    assert "log10_k = 1, 1.1, 2.07" in text
    res = {"hidden": [{"effect": "compressibility", "behind": "imperfect_gluing",
                       "parameter": "nu0", "at": {}, "inflation": 31.4,
                       "would_show_without": [0.4831], "would_show_at": [0.4065],
                       "separating_test": "a lubricated (slip-end) compression test"}]}
    text = "\n".join(_limit_lines(res))
    assert ("**compressibility could hide behind imperfect_gluing**: without "
            "imperfect_gluing in the model, nu0 would show from 0.4831; beside it, only "
            "from 0.4065 (its variance inflated 31.4 times" in text)
    assert "would tell: a lubricated (slip-end) compression test." in text
    res["hidden"][0].update(inflation=float("inf"), would_show_at=[])  # hidden whole
    text = "\n".join(_limit_lines(res))
    assert ("beside it, no allowed value would (these tests cannot tell the two apart); "
            "would tell" in text and "inf times" not in text)


def test_the_report_says_when_the_effect_just_added_lost_its_place():
    """report.md's round line: an effect dropped right after being added is said to have
    lost its place on the re-test from the joint fit (open-world-11)."""
    from diagnosis.report import _round_lines

    row = {"effect": "compressibility", "score": 62.1, "delta_bic": -120.0,
           "p_value": 4.5e-29, "significant": True, "parameters": {"nu0": 0.4884}}
    lines = _round_lines({"from": "imperfect_gluing+artefacts", "added": "compressibility",
                          "dropped": ["compressibility"], "table": [row]})
    assert lines[0] == ("From **imperfect_gluing+artefacts**: added compressibility, dropped "
                        "compressibility (it lost its place when re-tested beside the others "
                        "from the joint fit's values)")
    assert "| compressibility | 62.1 | -120.0 | 4.5e-29 | yes | nu0 = 0.4884 |" in lines
    plain = _round_lines({"from": "base", "added": None, "dropped": [], "table": []})
    assert plain[0] == "From **base**: added nothing" and plain[-1] == ""


def test_a_fit_whose_gauss_newton_start_cannot_be_solved_starts_nearer_its_design_point():
    """y = mu a + beta b, recorded at mu = 2, beta = 0.2, by a model whose solver fails for
    beta > 0.15 (as a strong relaxation at a short time makes the FE Newton fail).  The
    score's Gauss-Newton start (beta 0.2, exact on this linear model) cannot be solved:
    without a fallback the effect is left out (None); with its design point (beta 0) the
    fit starts half-way back (beta 0.1, solvable), and ends at the solvable edge, the
    constrained least-squares optimum (beta 0.15, mu by least squares there; 1e-3)."""
    import pandas as pd

    from diagnosis.screen import at_point
    from diagnosis.selection import Context, _fit
    from diagnosis.sharing import share_with

    sim, obs, a, b, current = _problem(0.2)
    tried = []

    def predict(values, names, solve=sim.predict):
        tried.append(float(values[EFF]))
        if values[EFF] > 0.15:
            raise RuntimeError("Newton failed")
        return solve(values, names)

    solver = types.SimpleNamespace(predict=predict, nu0=0.49)
    s = score(solver, _Obs(obs), np.ones(40), current, _Effect, {"beta_0": 0.0}, [MU],
              a[:, None])
    assert abs(s.start[EFF] - 0.2) < 1e-10
    ctx = Context(solver, pd.DataFrame(obs), np.ones(40), {"linear": _Effect}, [MU], 1e-3,
                  10.0, 40, share_with(None))
    assert _fit(ctx, s.start, ["linear"], "linear", 40) is None
    tried.clear()
    f = _fit(ctx, s.start, ["linear"], "linear", 40, at_point(current.values, s.point))
    assert tried[0] == pytest.approx(0.2) and tried[1] == pytest.approx(0.1)
    mu_edge = float(a @ (obs["value"] - 0.15 * b) / (a @ a))
    assert f.values[EFF] == pytest.approx(0.15, abs=1e-3)
    assert f.values[MU] == pytest.approx(mu_edge, abs=1e-3)


def test_the_score_of_an_effect_at_its_bound_is_one_sided():
    """Recorded at beta = -0.1 with beta bounded below by its neutral 0 (a relaxation, a
    softening or a second Ogden term cannot be negative): the two-sided Gauss-Newton step
    would promise the chi-square of beta = -0.1, which a fit clipped to the bound cannot
    have (open-world-32: second Ogden terms scored at up to 3400 whose fits ended at
    mu_1 = 0 with nothing gained).  The score is the one-sided statistic: nothing (1e-9),
    beta held at 0, mu the least-squares fit of the base alone (1e-10); at beta = +0.1 the
    step is taken as before, exact on this linear model."""
    sim, obs, a, b, current = _problem(-0.1)
    s = score(sim, _Obs(obs), np.ones(40), current, _Effect, {"beta_0": 0.0}, [MU],
              a[:, None])
    assert s.lm < 1e-9 and s.start[EFF] == 0.0
    assert abs(s.start[MU] - float(a @ obs["value"] / (a @ a))) < 1e-10
    # the two-sided reduction is kept beside it (what later rounds are offered by): the
    # data are exact, so the unbounded step removes all the base's misfit (1e-9)
    resid = obs["value"] - float(a @ obs["value"] / (a @ a)) * a
    assert abs(s.lm_free - float(resid @ resid)) < 1e-9
    sim, obs, a, b, current = _problem(0.1)
    s = score(sim, _Obs(obs), np.ones(40), current, _Effect, {"beta_0": 0.0}, [MU],
              a[:, None])
    resid = obs["value"] - float(a @ obs["value"] / (a @ a)) * a  # the base's best misfit
    assert abs(s.lm - float(resid @ resid)) < 1e-9
    assert abs(s.start[EFF] - 0.1) < 1e-10 and abs(s.start[MU] - 2.0) < 1e-10


def test_compressibility_scores_only_below_the_assumed_nu0():
    """In a diagnosis (``library(kind, nu0)``) compressibility ranges below the assumed nu0
    only: a misfit that asks for a stiffer volumetric response (nu0 up) scores nothing, one
    that asks for a lower nu0 scores its whole least-squares gain.  Exact on a linear model
    y = mu a + (nu0 - 0.49) b, against the closed-form gain (1e-9)."""
    from diagnosis.effects import library

    nu = Param("nu0")
    comp = library("fe", 0.49)["compressibility"]
    assert comp.bounds(nu) == (0.2, 0.49)
    assert library("fe")["compressibility"].bounds(nu) == (0.2, 0.4999)  # generators: both
    assert library("fe", 0.49)["viscoelastic"] is library("fe")["viscoelastic"]
    x = np.linspace(0.0, 1.0, 40)
    a, b = x, x**2

    def predict(values, names):
        cols = {MU: a, nu: b}
        jac = np.column_stack([cols[n] for n in names]) if names else np.zeros((x.size, 0))
        return types.SimpleNamespace(y=values[MU] * a + (values[nu] - 0.49) * b,
                                     jacobian=jac)

    sim = types.SimpleNamespace(predict=predict, nu0=0.49)
    for shift in (0.05, -0.05):  # the data's nu0 above, then below the assumed one
        data = 2.0 * a + shift * b
        current = types.SimpleNamespace(values={MU: 1.0, nu: 0.49},
                                        prediction=predict({MU: 1.0, nu: 0.49}, []).y)
        s = score(sim, _Obs({"value": data}), np.ones(40), current, comp, {"nu0": 0.49},
                  [MU], a[:, None])
        (m,), *_ = np.linalg.lstsq(a[:, None], data, rcond=None)
        gain = float(np.sum((data - m * a) ** 2))  # the joint fit is exact: all of it
        assert s.lm_free == pytest.approx(gain, rel=1e-9)
        assert s.lm == (pytest.approx(gain, rel=1e-9) if shift < 0 else 0.0)


def test_a_later_round_scores_an_effect_at_its_neutral_point_too():
    """A later round scores each candidate at the design point that won the first round;
    when that point is of finite size (nu0 0.45) it scores it at the neutral point (the
    assumed nu0) too.  Model y = mu a + q(nu0) b with q = nu0 - 0.49 above 0.46 and flat
    (-0.03) below, recorded at nu0 0.48: from 0.45 no step can see nu0 (its column is zero
    there, score 0: open-world-39's seed-14 world058, a compressibility beside a glue layer
    scored 0 from 0.45 and worth LRT 37 from the assumed nu0); from the neutral point the
    score is the closed-form least-squares gain (1e-9) and the fit reaches 0.48 (1e-6)."""
    import pandas as pd

    from diagnosis.effects import library
    from diagnosis.screen import Score
    from diagnosis.selection import Context, Round, run_round
    from diagnosis.sharing import share_with

    nu = Param("nu0")
    x = np.linspace(0.0, 1.0, 40)
    a, b = x, x**2

    def predict(values, names):
        v = values[nu]
        cols = {MU: a, nu: b * float(v >= 0.46)}
        jac = np.column_stack([cols[n] for n in names]) if names else np.zeros((x.size, 0))
        return types.SimpleNamespace(y=values[MU] * a + max(v - 0.49, -0.03) * b,
                                     jacobian=jac)

    sim = types.SimpleNamespace(predict=predict, nu0=0.49)
    data = 2.0 * a - 0.01 * b
    sigma = np.full(40, 1e-4)
    lib = library("fe", 0.49)
    ctx = Context(sim, pd.DataFrame({"value": data}), sigma, lib, [MU], 1e-3, 10.0, 40,
                  share_with(None))
    current = types.SimpleNamespace(values={MU: 2.0, nu: 0.49},
                                    prediction=predict({MU: 2.0, nu: 0.49}, []).y)
    comp = lib["compressibility"]
    at_finite = score(sim, _Obs({"value": data}), sigma, current, comp, {"nu0": 0.45}, [MU],
                      a[:, None])
    assert at_finite.lm == 0.0  # what the round saw before
    first = Round([], {"compressibility": Score("compressibility", 1.0, 1, {},
                                                {"nu0": 0.45})}, {}, [],
                  alive=["compressibility"])
    rnd = run_round(ctx, current, [], ["compressibility"], a[:, None], first=first)
    s = rnd.scores["compressibility"]
    assert s.point == {"nu0": 0.49}
    r = data / sigma - float(a @ data / (a @ a)) * a / sigma  # the base's best misfit
    assert s.lm == pytest.approx(float(r @ r), rel=1e-9)
    assert rnd.fits["compressibility"].values[nu] == pytest.approx(0.48, abs=1e-6)
