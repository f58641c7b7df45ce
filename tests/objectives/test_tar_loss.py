"""TARLoss: the LossModule wrapper on real ``[B, L]`` segments from a TorchRL replay buffer."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from objective_helpers import tar_loss
from tar_reference import ref_segment_loss, ref_weights
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, SliceSampler, TensorDictReplayBuffer
from torchrl.objectives import BCLoss, LossModule

from tar_rl import WEIGHTINGS, MixSchedule, TARLoss
from tar_rl.objectives import PerturbedTarget, PerturbParams

OBS, ACT, L = 5, 3, 6
LENGTHS = (3, 9, 4, 12, 7, 2)  # shorter than L somewhere, so the sampler pads


def make_actor(seed: int = 0) -> TensorDictModule:
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(OBS, 16), nn.Tanh(), nn.Linear(16, ACT))
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def make_loss(weighting: str = "tar", seed: int = 0, **kwargs) -> TARLoss:
    return tar_loss(BCLoss(make_actor(seed), loss_function="mse", reduction="none"), weighting, **kwargs)


def trajectories() -> TensorDict:
    g = torch.Generator().manual_seed(1)
    parts = []
    for episode, n in enumerate(LENGTHS):
        done = torch.zeros(n, 1, dtype=torch.bool)
        done[-1] = True
        parts.append(
            TensorDict(
                {
                    "observation": torch.randn(n, OBS, generator=g),
                    "action": torch.rand(n, ACT, generator=g) * 2 - 1,
                    "episode": torch.full((n,), episode),
                    "step": torch.arange(n),  # with episode_length: what dro_time reads
                    "episode_length": torch.full((n,), n),
                    ("next", "done"): done,
                },
                [n],
            )
        )
    return torch.cat(parts)


@pytest.fixture(scope="module")
def segments() -> TensorDict:
    """A [B, L] batch from SliceSampler(pad_output=True), with padding in it."""
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(100),
        sampler=SliceSampler(slice_len=L, traj_key="episode", strict_length=False, pad_output=True),
        batch_size=16 * L,
    )
    buffer.extend(trajectories())
    torch.manual_seed(3)
    batch = buffer.sample().reshape(-1, L)
    mask = batch["collector", "mask"]
    assert mask.dtype == torch.bool and mask.shape == (16, L)
    assert (~mask).any() and mask.any(-1).all(), "the fixture must contain padded steps"
    return batch


def hand_step_losses(actor: TensorDictModule, batch: TensorDict) -> torch.Tensor:
    """Per-step MSE computed directly from the network, [B, L]."""
    return (actor.module(batch["observation"]) - batch["action"]).square().mean(-1)


class TestAgainstHandWeightedLoss:
    """TARLoss(BCLoss) equals Eq. 2 with the reference weights, in value and in gradient."""

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    @pytest.mark.parametrize("mix", [1.0, 0.4])
    def test_value_and_gradient(self, segments, cap, mix):
        start, ramp = 10, 10  # step 14 of this schedule is alpha = 0.4
        schedule = MixSchedule(start=0 if mix == 1.0 else start, ramp=0 if mix == 1.0 else ramp)
        loss = make_loss(gamma=1.5, w_max=2.0, cap=cap, schedule=schedule)
        loss.schedule_step.fill_(0 if mix == 1.0 else 14)
        actor = loss.inner.actor_network
        params = list(actor.parameters())
        assert {id(p) for p in params} <= {id(p) for p in loss.parameters()}

        out = loss(segments)
        assert out["tar_mix"].item() == pytest.approx(mix)
        grads = torch.autograd.grad(out["loss_tar"], params)

        steps = hand_step_losses(actor, segments)
        valid = segments["collector", "mask"]
        w = torch.tensor(ref_weights(steps.detach().tolist(), valid.tolist(), gamma=1.5, w_max=2.0, cap=cap, mix=mix))
        expected_value = ref_segment_loss(steps.detach().tolist(), w.tolist(), valid.tolist())
        assert out["loss_tar"].item() == pytest.approx(expected_value, rel=1e-5)
        n_valid = valid.sum(-1)
        hand = ((w * steps * valid).sum(-1) / n_valid).mean()  # every fixture segment has a valid step
        expected_grads = torch.autograd.grad(hand, params)
        for got, want in zip(grads, expected_grads):
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)

    def test_uniform_is_the_masked_mean(self, segments):
        loss = make_loss("uniform")
        out = loss(segments)
        steps = hand_step_losses(loss.inner.actor_network, segments).detach()
        valid = segments["collector", "mask"]
        expected = ((steps * valid).sum(-1) / valid.sum(-1)).mean()
        assert out["loss_tar"].item() == pytest.approx(expected.item(), rel=1e-6)
        assert out["uniform_loss"].item() == pytest.approx(expected.item(), rel=1e-6)
        assert out["weight_ess"].item() == pytest.approx(1.0)
        assert out["weight_max"].item() == 1.0

    def test_segments_without_valid_steps_do_not_count(self, segments):
        batch = segments.clone()
        batch["collector", "mask"][:4] = False
        batch["action"][:4] = float("nan")  # padded values must not leak in
        out = make_loss()(batch)
        steps = hand_step_losses(make_actor(), batch).detach()
        valid = batch["collector", "mask"]
        w = ref_weights(steps.nan_to_num(0).tolist(), valid.tolist())
        expected = ref_segment_loss(steps.nan_to_num(0).tolist(), w, valid.tolist())
        assert out["loss_tar"].item() == pytest.approx(expected, rel=1e-5)


class TestConventions:
    """TorchRL LossModule conventions: keys, outputs, state, no input mutation."""

    def test_single_loss_output_and_diagnostics(self, segments):
        out = make_loss()(segments)
        loss_keys = [k for k in out.keys() if k.startswith("loss")]
        assert loss_keys == ["loss_tar"]
        for key in ("tar_mix", "weight_max", "weight_ess", "uniform_loss", "schedule_step"):
            assert key in out.keys()
            assert not out[key].requires_grad
        assert out["loss_tar"].requires_grad
        assert 0 < out["weight_ess"].item() <= 1
        assert out["weight_max"].item() > 1  # TAR is not uniform on these losses

    def test_does_not_mutate_input(self, segments):
        batch = segments.clone()
        before = batch.clone()
        for name in WEIGHTINGS:
            perturb = {"perturb_fraction": 1.0, "perturb_scale": 1.0} if WEIGHTINGS[name].perturb else {}
            make_loss(name, **perturb)(batch)
        assert set(batch.keys(True, True)) == set(before.keys(True, True))
        for key in before.keys(True, True):
            torch.testing.assert_close(batch[key], before[key], equal_nan=True)

    def test_set_keys_and_in_keys(self, segments):
        loss = make_loss()
        assert ("collector", "mask") in loss.in_keys and "observation" in loss.in_keys
        batch = segments.clone()
        batch["is_real"] = batch["collector", "mask"]
        del batch["collector", "mask"]
        loss.set_keys(valid="is_real")
        assert "is_real" in loss.in_keys
        torch.testing.assert_close(loss(batch)["loss_tar"], make_loss()(segments)["loss_tar"])
        with pytest.raises(ValueError, match="not an accepted tensordict key"):
            loss.set_keys(mask="x")

    def test_missing_mask_means_all_valid(self, segments):
        batch = segments.exclude(("collector", "mask"))
        full = segments.clone()
        full["collector", "mask"] = torch.ones(full.shape, dtype=torch.bool)
        torch.testing.assert_close(make_loss()(batch)["loss_tar"], make_loss()(full)["loss_tar"])

    def test_return_weights(self, segments):
        out = make_loss(return_weights=True)(segments)
        w = out["weights"]
        valid = segments["collector", "mask"]
        assert w.shape == valid.shape and not w.requires_grad
        assert (w[~valid] == 0).all()
        torch.testing.assert_close((w * valid).sum(-1) / valid.sum(-1), torch.ones(w.shape[0]))

    def test_state_dict_round_trip(self, segments):
        loss = make_loss("shuffle", seed=7)
        for _ in range(3):
            loss(segments)["loss_tar"].backward()
        state = loss.state_dict()
        assert int(state["schedule_step"]) == 3
        other = make_loss("shuffle", seed=123)
        other.load_state_dict(state)
        assert int(other.schedule_step) == 3
        a, b = loss(segments), other(segments)
        torch.testing.assert_close(a["loss_tar"], b["loss_tar"])  # same shuffle drawn: same RNG state


class TestSchedule:
    def test_before_start_every_weighting_is_uniform(self, segments):
        for name in WEIGHTINGS:
            perturb = {"perturb_scale": 1.0} if WEIGHTINGS[name].perturb else {}
            out = make_loss(name, schedule=MixSchedule(start=5, ramp=5), **perturb)(segments)
            assert out["tar_mix"].item() == 0.0
            torch.testing.assert_close(out["loss_tar"], out["uniform_loss"])

    def test_step_advances_only_in_training_with_grad(self, segments):
        loss = make_loss(schedule=MixSchedule(start=1, ramp=2))
        mixes = [loss(segments)["tar_mix"].item() for _ in range(4)]
        assert mixes == [0.0, 0.0, 0.5, 1.0]
        with torch.no_grad():
            loss(segments)
        loss.eval()
        loss(segments)
        assert int(loss.schedule_step) == 4
        loss.train()
        manual = make_loss(schedule=MixSchedule(start=1, ramp=2), auto_step=False)
        manual(segments)
        assert int(manual.schedule_step) == 0
        manual.advance(2)
        assert manual(segments)["tar_mix"].item() == 0.5


class TestChunksAndExtras:
    def test_event_dims_reduce_by_masked_mean(self):
        class ChunkLoss(LossModule):
            """Per-element L1 on [B, L, H, A], unreduced."""

            reduction = "none"

            def forward(self, td):
                return TensorDict({"loss_chunk": (td["pred"] - td["target"]).abs()}, [])

        g = torch.Generator().manual_seed(0)
        b, h = 3, 4
        td = TensorDict(
            {
                "pred": torch.randn(b, L, h, ACT, generator=g),
                "target": torch.randn(b, L, h, ACT, generator=g),
                "chunk_valid": torch.rand(b, L, h, generator=g) > 0.3,
            },
            [b, L],
        )
        td["chunk_valid"][..., 0] = True
        loss = tar_loss(ChunkLoss(), "uniform", return_weights=True)
        loss.set_keys(event_valid="chunk_valid")
        got = loss(td)["loss_tar"]
        err = (td["pred"] - td["target"]).abs().mean(-1)  # [b, L, h]
        per_step = [
            [
                sum(e for e, v in zip(err[i, t].tolist(), td["chunk_valid"][i, t].tolist()) if v)
                / sum(td["chunk_valid"][i, t].tolist())
                for t in range(L)
            ]
            for i in range(b)
        ]
        assert got.item() == pytest.approx(sum(sum(r) / L for r in per_step) / b, rel=1e-6)
        plain = tar_loss(ChunkLoss(), "uniform")(td)["loss_tar"]
        assert plain.item() == pytest.approx(err.mean().item(), rel=1e-6)

    def test_dim_losses_are_the_masked_mean_over_the_other_event_dims(self):
        class Given(LossModule):
            reduction = "none"

            def forward(self, td):
                return TensorDict({"loss_chunk": td["elements"]}, [])

        # one segment of 2 steps, a horizon of 3, 2 action dims; NaN on a padded entry
        elements = torch.tensor(
            [[[[1.0, 10.0], [3.0, 20.0], [5.0, 60.0]], [[2.0, 4.0], [6.0, 8.0], [float("nan"), 1e6]]]]
        )
        valid = torch.tensor([[[True, True, True], [True, True, False]]])
        td = TensorDict({"elements": elements, "chunk_valid": valid}, [1, 2])
        loss = tar_loss(Given(), "uniform")
        loss.set_keys(event_valid="chunk_valid")
        steps, dims = loss.step_and_dim_losses(td)
        # step 0: dim 0 (1 + 3 + 5) / 3 = 3, dim 1 (10 + 20 + 60) / 3 = 30; step 1: (2 + 6) / 2 = 4, (4 + 8) / 2 = 6
        torch.testing.assert_close(dims, torch.tensor([[[3.0, 30.0], [4.0, 6.0]]]))
        torch.testing.assert_close(steps, torch.tensor([[16.5, 5.0]]))  # the mean over valid elements
        torch.testing.assert_close(steps, loss.step_losses(td))
        plain = tar_loss(Given(), "uniform")  # no event mask: plain means
        _, dims = plain.step_and_dim_losses(td[:, :1])
        torch.testing.assert_close(dims, torch.tensor([[[3.0, 30.0]]]))
        per_step = TensorDict({"elements": elements[..., 0, 0]}, [1, 2])  # one loss per step: no dims
        steps, dims = plain.step_and_dim_losses(per_step)
        assert dims is None and steps.tolist() == [[1.0, 2.0]]

    def test_extra_scalar_losses_are_added_unweighted(self, segments):
        class WithKL(LossModule):
            reduction = "none"

            def forward(self, td):
                per_step = td["observation"].square().mean(-1)
                return TensorDict({"loss_main": per_step, "loss_kl": torch.tensor(0.25)}, [])

        out = tar_loss(WithKL(), "uniform", loss_key="loss_main")(segments)
        valid = segments["collector", "mask"]
        steps = segments["observation"].square().mean(-1)
        expected = ((steps * valid).sum(-1) / valid.sum(-1)).mean() + 0.25
        assert out["loss_tar"].item() == pytest.approx(expected.item(), rel=1e-6)
        assert out["aux_loss_kl"].item() == 0.25


class TestPerturbationControls:
    def test_zero_scale_is_uniform(self, segments):
        for name in ("perturb_high", "perturb_low"):
            out = make_loss(name, perturb_scale=0.0)(segments)
            torch.testing.assert_close(out["loss_tar"], make_loss("uniform")(segments)["loss_tar"])

    def test_noise_lands_on_the_selected_steps(self, segments):
        """Record what the inner loss sees: only the chosen steps' actions differ."""
        seen = []

        class Recorder(LossModule):
            reduction = "none"

            def forward(self, td):
                seen.append(td["action"].clone())
                return TensorDict({"loss_x": td["observation"].square().mean(-1) + td["action"].sum(-1) * 0}, [])

        loss = tar_loss(Recorder(), "perturb_high", perturb_fraction=0.5, perturb_scale=1.0)
        out = loss(segments)
        clean, noisy = seen
        changed = (clean != noisy).any(-1)
        valid = segments["collector", "mask"]
        assert not (changed & ~valid).any()
        expected_count = torch.floor(0.5 * valid.sum(-1) + 0.5)
        torch.testing.assert_close(changed.sum(-1).float(), expected_count)
        steps = segments["observation"].square().mean(-1).masked_fill(~valid, -math.inf)
        for i in range(valid.shape[0]):  # the chosen steps are the highest-loss ones
            k = int(expected_count[i])
            top = set(steps[i].topk(k).indices.tolist()) if k else set()
            assert set(changed[i].nonzero().flatten().tolist()) == top
        assert out["perturbed_fraction"].item() == pytest.approx((changed.sum() / valid.sum()).item())

    @pytest.mark.parametrize("which", ["high", "low"])
    def test_the_control_needs_its_wrapper(self, which):
        """Without a PerturbedTarget of its kind the control's weights alone would be the uniform mean: refused."""
        inner = BCLoss(make_actor(), loss_function="mse", reduction="none")
        with pytest.raises(ValueError, match=rf"perturb_{which} weighting trains on a corrupted target.*BCLoss\."):
            TARLoss(inner, f"perturb_{which}")
        other = "low" if which == "high" else "high"
        with pytest.raises(ValueError, match=rf"PerturbedTarget\(inner, '{which}'.*got PerturbedTarget \({other}\)"):
            TARLoss(PerturbedTarget(inner, other, PerturbParams()), f"perturb_{which}")

    def test_the_wrapper_resumes_its_draws(self, segments):
        """The wrapper's generator is in the objective's state: a copy loaded from it draws the same numbers."""
        loss = make_loss("perturb_high", perturb_fraction=0.5, perturb_scale=1.0, seed=4)
        loss(segments)
        state = copy.deepcopy(loss.state_dict())
        resumed = make_loss("perturb_high", perturb_fraction=0.5, perturb_scale=1.0, seed=4)
        resumed.load_state_dict(state)
        fresh = make_loss("perturb_high", perturb_fraction=0.5, perturb_scale=1.0, seed=4)
        expected, got, first = loss(segments), resumed(segments), fresh(segments)
        assert torch.equal(got["loss_tar"], expected["loss_tar"])
        assert not torch.equal(first["loss_tar"], expected["loss_tar"])  # the second draw differs from the first


@pytest.mark.parametrize("name", sorted(WEIGHTINGS))
def test_every_registered_weighting_trains(segments, name):
    loss = make_loss(name, return_weights=True)
    optim = torch.optim.SGD(loss.parameters(), lr=0.1)
    out = loss(segments)
    out["loss_tar"].backward()
    optim.step()
    assert torch.isfinite(out["loss_tar"])
    valid = segments["collector", "mask"]
    w = out["weights"]
    assert (w >= 0).all() and (w[~valid] == 0).all()
    torch.testing.assert_close((w * valid).sum(-1) / valid.sum(-1), torch.ones(w.shape[0]))


class TestBadInput:
    def test_flat_batch(self, segments):
        with pytest.raises(ValueError, match=r"batch shape \[B, L\].*reshape"):
            make_loss()(segments.reshape(-1))

    def test_mask_dtype_and_shape(self, segments):
        batch = segments.clone()
        batch["collector", "mask"] = batch["collector", "mask"].float()
        with pytest.raises(TypeError, match=r"must be torch\.bool"):
            make_loss()(batch)
        batch = segments.clone()
        batch.set("bad_mask", torch.ones(segments.shape[0], L, 2, dtype=torch.bool))
        loss = make_loss()
        loss.set_keys(valid="bad_mask")
        with pytest.raises(ValueError, match="expected the batch shape"):
            loss(batch)

    def test_nan_loss_at_valid_step(self, segments):
        batch = segments.clone()
        valid = batch["collector", "mask"]
        i, t = valid.nonzero()[0].tolist()
        batch["action"][i, t, 0] = float("nan")
        for name in ("tar", "uniform"):
            with pytest.raises(ValueError, match="non-finite"):
                make_loss(name)(batch)

    @pytest.mark.parametrize("name", sorted(WEIGHTINGS))
    def test_nonfinite_propagate_makes_the_loss_non_finite(self, segments, name):
        # Finite losses: the same loss and gradient as the default (bit for bit). A NaN at one valid
        # step: no exception, a non-finite loss (for the training loop's own handling).
        raising, propagating = make_loss(name), make_loss(name, nonfinite="propagate")
        a, b = raising(segments), propagating(segments)
        assert torch.equal(a["loss_tar"], b["loss_tar"])
        a["loss_tar"].backward()
        b["loss_tar"].backward()
        for p, q in zip(raising.parameters(), propagating.parameters()):
            assert torch.equal(p.grad, q.grad)
        batch = segments.clone()
        i, t = batch["collector", "mask"].nonzero()[0].tolist()
        batch["action"][i, t, 0] = float("nan")
        assert torch.isnan(propagating(batch)["loss_tar"])
        with pytest.raises(ValueError, match="nonfinite must be one of"):
            make_loss(name, nonfinite="skip")

    def test_unknown_weighting(self):
        with pytest.raises(ValueError, match=r"unknown weighting 'tar2'.*uniform, tar"):
            make_loss("tar2")

    def test_reduced_inner_loss(self):
        with pytest.raises(ValueError, match="reduction='none'"):
            tar_loss(BCLoss(make_actor(), loss_function="mse"))

    def test_inner_not_a_loss_module(self):
        with pytest.raises(TypeError, match="LossModule"):
            tar_loss(nn.Linear(2, 2))

    def test_bad_hyper_parameters(self):
        with pytest.raises(ValueError, match="gamma"):
            make_loss(gamma=0.0)
        with pytest.raises(ValueError, match="w_max >= 1"):
            make_loss(cap="exact", w_max=0.5)
        with pytest.raises(ValueError, match="perturb_fraction"):
            make_loss("perturb_high", perturb_fraction=1.5)
        with pytest.raises(TypeError, match="MixSchedule"):
            make_loss(schedule=(20_000, 30_000))

    def test_ambiguous_inner_output(self, segments):
        class TwoLosses(LossModule):
            reduction = "none"

            def __init__(self):
                super().__init__()
                self.scale = nn.Parameter(torch.ones(()))

            def forward(self, td):
                x = td["observation"].mean(-1) * self.scale
                return TensorDict({"loss_a": x, "loss_b": x}, [])

        with pytest.raises(ValueError, match="loss_key"):
            tar_loss(TwoLosses())(segments)
        # a differentiable per-step extra loss would have to be weighted: refused
        with pytest.raises(ValueError, match="must be scalars"):
            tar_loss(TwoLosses(), loss_key="loss_a")(segments)

    def test_compacted_inner_output(self, segments):
        inner = BCLoss(make_actor(), loss_function="mse", reduction="none")
        inner.set_keys(pad_mask="pad")
        batch = segments.clone()
        batch["pad"] = ~batch["collector", "mask"]
        with pytest.raises(ValueError, match="pad_mask"):
            tar_loss(inner)(batch)


class TestCompile:
    @pytest.mark.parametrize("name", ["tar", "uniform"])
    def test_fullgraph_matches_eager(self, segments, name):
        eager, compiled_loss = make_loss(name), make_loss(name)
        compiled = torch.compile(compiled_loss, backend="aot_eager", fullgraph=True)
        for _ in range(2):
            a, b = eager(segments), compiled(segments)
            torch.testing.assert_close(a["loss_tar"], b["loss_tar"])
            torch.testing.assert_close(a["weight_ess"], b["weight_ess"])
        assert int(compiled_loss.schedule_step) == 2
        bad = segments.clone()
        i, t = bad["collector", "mask"].nonzero()[0].tolist()
        bad["observation"][i, t] = float("inf")
        with pytest.raises(RuntimeError, match="non-finite"):
            compiled(bad)

    def test_compile_weights_setting(self, segments):
        with pytest.raises(ValueError, match="compile_weights"):
            make_loss(compile_weights="sometimes")
        # auto: eager on the CPU (compiled only for CUDA tensors with triton); never: eager everywhere
        cpu = torch.device("cpu")
        assert make_loss()._weight_function(cpu) is WEIGHTINGS["tar"].weights
        assert make_loss(compile_weights="never")._weight_function(cpu) is WEIGHTINGS["tar"].weights
        # uniform and the stochastic controls always run eagerly
        for name in ("uniform", "shuffle", "random", "perturb_high"):
            assert make_loss(name, compile_weights="always")._weight_function(cpu) is WEIGHTINGS[name].weights

    def test_each_loss_owns_its_compiled_weighting_and_pickles_after_compiling(self):
        import copy
        import pickle

        from tar_rl.objectives import tar_loss

        assert not hasattr(tar_loss, "_COMPILED")  # nothing compiled is kept by the module
        cpu = torch.device("cpu")
        first, second = make_loss(compile_weights="always"), make_loss(compile_weights="always")
        compiled = first._weight_function(cpu)
        assert compiled is not WEIGHTINGS["tar"].weights
        assert first._weight_function(cpu) is compiled  # built once, at its first use
        assert second._weight_function(cpu) is not compiled
        for twin in (pickle.loads(pickle.dumps(first)), copy.deepcopy(first)):
            assert twin._weight_function(cpu) not in (compiled, WEIGHTINGS["tar"].weights)
        assert first._weight_function(cpu) is compiled

    @pytest.mark.slow
    @pytest.mark.parametrize("name", ["tar", "invert", "tilted", "truncate", "keyframe", "focal"])
    def test_compiled_weighting_matches_eager_through_the_schedule(self, segments, name):
        from torch._dynamo.utils import counters

        schedule = MixSchedule(start=1, ramp=3)  # alpha 0, 0, 1/3, 2/3, 1 over five steps
        # segments of 6 steps: truncate's default q = 0.1 would drop nothing (floor(0.6) = 0)
        kw = {"truncate_fraction": 0.3} if name == "truncate" else {}
        eager = make_loss(name, schedule=schedule, return_weights=True, compile_weights="never", **kw)
        compiled = make_loss(name, schedule=schedule, return_weights=True, compile_weights="always", **kw)
        assert compiled._weight_function(torch.device("cpu")) is not WEIGHTINGS[name].weights
        graphs = counters["stats"]["unique_graphs"]
        for _ in range(5):
            a, b = eager(segments), compiled(segments)
            torch.testing.assert_close(b["weights"], a["weights"], rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(b["loss_tar"], a["loss_tar"], rtol=1e-5, atol=1e-6)
            ga = torch.autograd.grad(a["loss_tar"], list(eager.parameters()))
            gb = torch.autograd.grad(b["loss_tar"], list(compiled.parameters()))
            for x, y in zip(ga, gb):
                torch.testing.assert_close(y, x, rtol=1e-4, atol=1e-6)
        assert float(a["tar_mix"]) == 1.0  # the last step weighted at full strength: not the uniform mean
        assert not torch.allclose(a["weights"], segments["collector", "mask"].to(a["weights"].dtype))
        assert counters["stats"]["unique_graphs"] - graphs <= 1, "the weighting is recompiled as the schedule moves"
        bad = segments.clone()
        i, t = bad["collector", "mask"].nonzero()[0].tolist()
        bad["observation"][i, t] = float("nan")
        with pytest.raises(RuntimeError, match="non-finite"):
            compiled(bad)

    @pytest.mark.slow
    def test_inductor_training_step(self, segments):
        eager, compiled_loss = make_loss(), make_loss()
        compiled = torch.compile(compiled_loss)
        a, b = eager(segments), compiled(segments)
        torch.testing.assert_close(a["loss_tar"], b["loss_tar"], rtol=1e-5, atol=1e-6)
        ga = torch.autograd.grad(a["loss_tar"], list(eager.parameters()))
        gb = torch.autograd.grad(b["loss_tar"], list(compiled_loss.parameters()))
        for x, y in zip(ga, gb):
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)


@pytest.mark.gpu
@pytest.mark.parametrize("name", ["tar", "shuffle", "perturb_high", "keyframe", "focal"])
def test_cuda_matches_cpu(segments, name):
    cpu, gpu = make_loss(name, cap="exact"), make_loss(name, cap="exact").cuda()
    a, b = cpu(segments), gpu(segments.cuda())
    torch.testing.assert_close(a["loss_tar"], b["loss_tar"].cpu(), rtol=1e-4, atol=1e-6)
    assert b["loss_tar"].device.type == "cuda"
