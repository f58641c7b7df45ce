"""``TARLoss``: a TorchRL ``LossModule`` that owns the reduction of per-step losses over time.

The inner objective (any ``LossModule`` built with ``reduction="none"``, e.g. torchrl's
``BCLoss``) computes unreduced per-step losses on a ``[B, L]`` TensorDict of segments.
``TARLoss`` reduces any trailing event dimensions (action dims, chunk horizon) to ``[B, L]``,
weights the steps of each segment with a registered weighting (``"tar"`` by default, the
uniform mean, the paper's controls and the baselines from the literature by name) and returns
the segment loss of Eq. 2, averaged over the segments that have at least one valid step. Step and
element weightings take one path: the weighting scores the losses at its granularity (steps, or the
elements of each step), and each step's loss is the mean of its valid entries' weighted losses. Where
the inner loss returns a ranking signal beside its loss (``signal``, one value per step), a step
weighting scores the signal instead and still weights the loss. A
stateful weighting (``dro_time``) keeps its state in a module of ``TARLoss`` (:class:`WeightingState`),
updated on each training step. The perturbation controls' inner loss is the head's wrapped in
:class:`~tar_rl.objectives.supervision.PerturbedTarget` (built by the training job, or by hand), which
``TARLoss`` calls with the schedule's alpha.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.distributed as torch_dist
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.objectives import LossModule

from . import inner as inner_output
from .elementwise import element_mean
from .inner import segment_mean  # exported here too: Eq. 2's reduction is part of TARLoss's interface
from .schedule import MixSchedule
from .supervision import PerturbedTarget, target_key
from .weighting import Weighting, get_weighting

__all__ = ["COMPILE_MODES", "NONFINITE_MODES", "TARLoss", "WeightingState", "compiles_weights", "segment_mean"]

#: ``nonfinite`` of :class:`TARLoss`: what a NaN/inf per-step loss does (raise, or make ``loss_tar`` non-finite).
NONFINITE_MODES = ("raise", "propagate")
#: ``compile_weights`` of :class:`TARLoss`: ``auto`` (on CUDA, when triton is installed), ``always``, ``never``.
COMPILE_MODES = ("auto", "always", "never")


def _sum_over_ranks(stats: Tensor) -> Tensor:
    """``stats`` summed over the ranks of the process group (the state update's batch statistics)."""
    torch_dist.all_reduce(stats)
    return stats


def compiles_weights(compile_weights: str, device: torch.device) -> bool:
    """Whether ``TARLoss(compile_weights=...)`` compiles its weighting for tensors on ``device``:
    ``always``; ``auto`` for CUDA tensors when inductor can emit triton kernels; never for ``never``
    (and never for the weightings that always run eagerly, see :class:`TARLoss`)."""
    if compile_weights != "auto":
        return compile_weights == "always"
    if device.type != "cuda":
        return False
    from torch.utils._triton import has_triton  # cached

    return has_triton()


class WeightingState(nn.Module):
    """A weighting's state between training steps: the buffer ``value`` of a stateful weighting (``dro_time``:
    its ``[G]`` log group weights), nothing for the others.

    Args:
        initial: the state to start from (:attr:`Weighting.initial_state`), or ``None`` for a weighting
            without state (then the module holds no buffer and adds nothing to a ``state_dict()``).
    """

    def __init__(self, initial: Tensor | None) -> None:
        super().__init__()
        self.stateful = initial is not None
        if initial is not None:
            self.register_buffer("value", initial)

    def inputs(self, training_step: bool) -> dict:
        """What a stateful weighting reads besides the losses: ``state`` and ``reduce`` (the sum over the ranks
        of a distributed job on a training step, else ``None``); nothing for the others."""
        if not self.stateful:
            return {}
        distributed = training_step and torch_dist.is_available() and torch_dist.is_initialized()
        return {"state": self.value, "reduce": _sum_over_ranks if distributed else None}

    def weights(self, result: Tensor | tuple[Tensor, Tensor], training_step: bool) -> Tensor:
        """The weights of a weighting's ``result``; a stateful one's ``(weights, new_state)`` replaces the state
        on a training step only."""
        if not self.stateful:
            return result
        weights, state = result
        if training_step:
            self.value.copy_(state)
        return weights


class TARLoss(LossModule):
    """Time-Adaptive Reweighting around a per-step imitation loss (paper Sec. II).

    Args:
        inner (LossModule): computes per-step losses without reducing them, e.g.
            ``BCLoss(actor, loss_function="mse", reduction="none")`` or ``ACTLoss(model, reduction="none")``.
            Its output holds the per-step loss as a ``loss_*`` entry of shape ``[B, L, ...]`` (the input's
            batch shape, then any event dims). Its other ``loss_*`` entries are scalars, added unweighted
            (reported as ``aux_<key>``), or detached entries of the batch shape, which are diagnostics
            (reported as their mean over the valid steps, ``inner_<key>``); its entries not named ``loss*``
            are reported detached under their own names, but its ranking signal (``tensor_keys.signal``,
            below), which the weighting scores in place of the per-step loss.
        weighting (str): a name from :data:`tar_rl.objectives.WEIGHTINGS`: ``"tar"`` (default),
            ``"uniform"`` (Eq. 1), a control: ``"shuffle"``, ``"random"``, ``"invert"``,
            ``"perturb_high"``, ``"perturb_low"`` (these need ``inner`` wrapped in
            :class:`~tar_rl.objectives.supervision.PerturbedTarget` of their kind,
            ``PerturbedTarget(loss, "high", PerturbParams())``), a baseline from the literature
            (:mod:`~tar_rl.objectives.baselines`): ``"tilted"``, ``"truncate"``, ``"keyframe"``,
            ``"focal"``, ``"dro_time"``, or an element weighting (:mod:`~tar_rl.objectives.elementwise`):
            ``"tar_arm"``, ``"tar_dimnorm"``, which scores the per-element losses before the event dims
            are averaged (it needs event dims whose last axis holds the action dims).

    Keyword Args:
        params: the weighting's parameters, an instance of ``WEIGHTINGS[weighting].params``
            (:class:`~tar_rl.objectives.TARParams` for ``tar`` and its controls,
            :class:`~tar_rl.objectives.FocalParams` for ``focal``, ...); default: that class's defaults.
        schedule (MixSchedule): when the weighting is mixed in; default: fully on from the first step.
            Before ``schedule.start`` every weighting is the uniform mean.
        loss_key (NestedKey): the inner output holding the per-step loss; default: its only ``loss_*`` entry.
        seed (int): seeds the generator of the stochastic controls; its state is part of
            ``state_dict()`` so that a resumed run draws the same numbers.
        return_weights (bool): also return the ``[B, L]`` weights under ``"weights"``.
        auto_step (bool): advance the schedule by one on every forward pass made in training
            mode with gradients enabled (default). Set ``False`` with gradient accumulation and
            call :meth:`advance` once per optimiser step instead.
        compile_weights (str): run the weighting through ``torch.compile`` (its thirty tiny kernels fuse into a
            few, equal up to float rounding): ``"auto"`` (default) on CUDA with triton, ``"always"``, ``"never"``.
            Uniform, the stochastic controls and ``dro_time`` always run eagerly.
        nonfinite (str): what a NaN or infinite per-step loss at a valid step does: ``"raise"`` (default) a
            ``ValueError``; ``"propagate"`` makes ``loss_tar`` non-finite (the weights are computed as if that
            loss were 0), so that a training loop's own handling sees it after ``backward``, on every rank.

    Input: a TensorDict of batch shape ``[B, L]`` (segments x steps) holding what the inner loss reads and the
    validity mask ``tensor_keys.valid`` (``True`` on real steps; absent: every step is valid); for a weighting
    that reads time (``dro_time``) also ``tensor_keys.step`` and ``tensor_keys.episode_length`` (:attr:`time_keys`).

    State: ``schedule_step``, the weighting's state (module ``weighting_state``, a :class:`WeightingState`) and
    the controls' generator are in ``state_dict()``, so a resumed run continues them exactly. The state moves
    only on a training step (training mode, gradients enabled); in a distributed job its update's batch
    statistics are summed over the ranks, so every rank must call the loss on every training step.

    Output keys: ``loss_tar`` (the only differentiable entry) and the detached diagnostics
    ``tar_mix`` (alpha), ``weight_max``, ``weight_ess`` (mean over segments of the effective
    sample size ``(sum w)^2 / (M sum w^2)``, 1 for uniform weights), ``uniform_loss`` (Eq. 1
    on the same losses), ``schedule_step``; the inner loss's diagnostics (above; ``perturbed_fraction``
    for the perturbation controls); ``weights`` if asked.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.objectives import BCLoss
        >>> from tar_rl.objectives import TARParams
        >>> actor = TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["action"])
        >>> loss = TARLoss(BCLoss(actor, loss_function="mse", reduction="none"), "tar", params=TARParams(gamma=0.5))
        >>> data = TensorDict(
        ...     {"observation": torch.randn(4, 8, 3), "action": torch.randn(4, 8, 2),
        ...      ("collector", "mask"): torch.ones(4, 8, dtype=torch.bool)}, [4, 8])
        >>> out = loss(data)
        >>> out["loss_tar"].shape, sorted(k for k in out.keys() if k.startswith("loss"))
        (torch.Size([]), ['loss_tar'])
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys.

        Attributes:
            valid (NestedKey): bool ``[B, L]`` (or ``[B, L, 1]``) mask, ``True`` on real steps.
                Defaults to ``("collector", "mask")``.
            action (NestedKey): the supervision target that a
                :class:`~tar_rl.objectives.supervision.PerturbedTarget` inner loss (the ``perturb_*``
                controls) corrupts; set there too. Defaults to the inner loss's declared ``target_key``,
                else its ``action`` key (torchrl's BC losses), else ``"action"``.
            event_valid (NestedKey, optional): bool ``[B, L, ...]`` mask over the event dims of
                the per-step loss, ``True`` on real elements (e.g. the valid part of an action
                chunk near the end of a trajectory). The per-step loss is the mean over the
                valid elements. Defaults to ``None``: a plain mean over the event dims.
            step (NestedKey): integer ``[B, L]``, each step's index in its episode; read by the
                weightings that read time (``dro_time``). Defaults to ``"step"``.
            episode_length (NestedKey): integer ``[B, L]``, the length of each step's episode;
                read with ``step``. Defaults to ``"episode_length"``.
            signal (NestedKey): an entry of the inner loss's *output*, not of the batch: a detached ``[B, L]``
                ranking signal, one value per step, that the weighting scores in place of the per-step loss
                (the loss is still what is weighted); e.g. the ``flow`` head's implied action error. Absent
                from the output: the weighting scores the loss. An element weighting refuses it; a NaN or inf
                at a valid step is handled as a non-finite loss (``nonfinite``). Defaults to ``"signal"``.
        """

        valid: NestedKey = ("collector", "mask")
        action: NestedKey = "action"
        event_valid: NestedKey | None = None
        step: NestedKey = "step"
        episode_length: NestedKey = "episode_length"
        signal: NestedKey = inner_output.SIGNAL

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_tar", "tar_mix", "weight_max", "weight_ess", "uniform_loss", "schedule_step"]

    inner: LossModule

    def __init__(
        self,
        inner: LossModule,
        weighting: str = "tar",
        *,
        params=None,
        schedule: MixSchedule | None = None,
        loss_key: NestedKey | None = None,
        seed: int = 0,
        return_weights: bool = False,
        auto_step: bool = True,
        compile_weights: str = "auto",
        nonfinite: str = "raise",
    ) -> None:
        spec = get_weighting(weighting)
        params = _checked_params(spec, params)
        perturbed = isinstance(inner, PerturbedTarget)
        _check_arguments(inner.inner if perturbed else inner, schedule, compile_weights, nonfinite)
        _check_supervision(spec, inner)
        super().__init__()
        self.weighting, self.params = spec, params
        self.schedule = MixSchedule() if schedule is None else schedule
        self.loss_key, self.return_weights, self.auto_step = loss_key, return_weights, auto_step
        self.compile_weights, self.nonfinite = compile_weights, nonfinite
        self.register_buffer("schedule_step", torch.zeros((), dtype=torch.long))
        self.weighting_state = WeightingState(spec.initial_state(params) if spec.initial_state else None)
        self._generator = torch.Generator().manual_seed(seed)
        self._compiled_weights = None  # the weighting through torch.compile, built at its first use
        # A supervision transform (PerturbedTarget) takes the schedule's alpha and reads this loss's keys.
        self._perturbed = perturbed
        self.inner = inner
        self.set_keys(action=target_key(inner))
        shown = (
            k for k in getattr(inner, "out_keys", ()) if not str(k).startswith("loss") and k != self.tensor_keys.signal
        )
        self.out_keys = [*self.out_keys, *shown]
        self.out_keys += ["weights"] if return_weights else []

    # -- TorchRL plumbing -------------------------------------------------------------------

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._perturbed:  # it reads the same mask, target, event mask and ranking signal
            keys = self.tensor_keys
            self.inner.set_keys(valid=keys.valid, action=keys.action, event_valid=keys.event_valid, signal=keys.signal)

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = [*self.inner.in_keys, self.tensor_keys.valid, *self.time_keys]
        if self.tensor_keys.event_valid is not None:
            keys.append(self.tensor_keys.event_valid)
        return list(dict.fromkeys(keys))

    @property
    def time_keys(self) -> tuple[NestedKey, ...]:
        """The keys of each step's position in its episode (``step``, ``episode_length``) when the
        weighting reads time; empty otherwise."""
        if not self.weighting.reads_time:
            return ()
        return (self.tensor_keys.step, self.tensor_keys.episode_length)

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_compiled_weights"] = None  # a compiled function does not pickle: a copy compiles its own
        return state

    def get_extra_state(self) -> dict:
        return {"generator": self._generator.get_state()}

    def set_extra_state(self, state: dict) -> None:
        self._generator.set_state(state["generator"])

    @property
    def clean_inner(self) -> LossModule:
        """The head's own loss: the inner loss, or the loss a :class:`PerturbedTarget` inner loss wraps."""
        return self.inner.inner if self._perturbed else self.inner

    def advance(self, steps: int = 1) -> None:
        """Move the schedule on by ``steps`` optimiser steps (for ``auto_step=False``)."""
        self.schedule_step.add_(steps)

    # -- The objective ----------------------------------------------------------------------

    def step_losses(self, tensordict: TensorDictBase) -> Tensor:
        """The inner loss's per-step losses ``[B, L]`` (event dims reduced), unweighted, on the clean batch.

        For inspection (e.g. recording losses along whole demonstrations): it neither weights
        the steps nor advances the schedule.
        """
        return self.step_and_dim_losses(tensordict)[0]

    def step_and_dim_losses(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor | None]:
        """``(steps, dims)`` from one pass of the inner loss: ``steps`` as :meth:`step_losses`; ``dims``
        ``[B, L, A]``, each action dim's loss per step, the mean over the other event dims' valid entries (0 where
        a step has none), or ``None`` without event dims (:func:`~tar_rl.objectives.inner.dim_losses`). For
        inspection, like :meth:`step_losses`."""
        return self.inspect_steps(tensordict)[:2]

    def inspect_steps(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor | None, Tensor]:
        """``(steps, dims, ranked)`` from one pass of the inner loss on the clean batch: ``steps`` and ``dims`` as
        :meth:`step_and_dim_losses`, ``ranked`` ``[B, L]`` what a step weighting scores, the inner loss's ranking
        signal where it gives one, else ``steps`` (detached). For inspection: it neither weights the steps nor
        advances the schedule."""
        out = self.clean_inner(tensordict)
        key = inner_output.loss_entry(out, self.loss_key)
        steps = self._step_losses(out, key, tensordict)
        signal = inner_output.read_signal(out, self.tensor_keys.signal, tensordict)
        dims = inner_output.dim_losses(out, key, tensordict, self.tensor_keys.event_valid)
        return steps, dims, steps.detach() if signal is None else signal

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Weighted segment loss of Eq. 2 on a ``[B, L]`` TensorDict; does not modify it."""
        valid = inner_output.read_valid(tensordict, self.tensor_keys.valid)
        mix = self.schedule(self.schedule_step)
        training_step = self.training and torch.is_grad_enabled()
        out = self.inner(tensordict, mix) if self._perturbed else self.inner(tensordict)
        key = inner_output.loss_entry(out, self.loss_key)
        time = inner_output.read_time(tensordict, self.time_keys, self.weighting.name)
        inputs = {**time, **self.weighting_state.inputs(training_step)}
        signal = inner_output.read_signal(out, self.tensor_keys.signal, tensordict)
        loss, losses, weights = self._weigh(out, key, tensordict, valid, mix, inputs, training_step, signal)
        if signal is not None and self.nonfinite == "propagate":
            loss = loss + inner_output.nonfinite_term(signal, valid)
        extra, diagnostics = inner_output.other_entries(out, key, tensordict, valid, self.tensor_keys.signal)
        for value in extra:
            loss = loss + value
        with torch.no_grad():
            m = valid.to(weights.dtype)
            n_valid = m.sum(-1)
            square_sum = (weights.square() * m).sum(-1)
            ess = (weights * m).sum(-1).square() / (n_valid * square_sum).clamp_min(torch.finfo(weights.dtype).tiny)
            nonempty = n_valid > 0
            result = {
                "loss_tar": loss,
                "tar_mix": torch.as_tensor(mix, dtype=torch.float32),
                "weight_max": weights.detach().max(),
                "weight_ess": (ess * nonempty).sum() / nonempty.sum().clamp_min(1),
                "uniform_loss": segment_mean(losses.detach(), m, valid),
                "schedule_step": self.schedule_step.clone(),
                **diagnostics,
                **({"weights": weights.detach()} if self.return_weights else {}),
            }
        if self.auto_step and training_step:
            self.schedule_step.add_(1)
        return TensorDict(result, batch_size=[])

    # -- Helpers ----------------------------------------------------------------------------

    def _weigh(self, out, key, tensordict, valid, mix, inputs, training_step, signal) -> tuple[Tensor, Tensor, Tensor]:
        """``(loss, step losses, step weights)``: Eq. 2 with the weighting's weights, which see detached losses
        (the stop-gradient of Eq. 3), or the inner loss's detached ranking ``signal`` where it gives one. The
        weighting scores its entries (:meth:`_entries`: the steps, or the elements of each step); a step's loss
        is then the mean of its valid entries' ``weight * loss`` and its weight the mean of their weights (a step
        weighting's entry is the step itself)."""
        values, entry_valid = self._entries(out, key, tensordict, valid, signal)
        ranked = inner_output.scores(values, signal, entry_valid, self.tensor_keys.signal, self.nonfinite)
        scored = inner_output.scored(ranked, entry_valid, self.nonfinite)
        generator = self._generator if self.weighting.stochastic else None
        result = self._weight_function(values.device)(scored, entry_valid, self.params, mix, generator, **inputs)
        entry_weights = self.weighting_state.weights(result, training_step)
        steps = valid.ndim
        weighted = element_mean(entry_weights.to(values.dtype) * values, entry_valid, steps)  # [B, L]
        loss = segment_mean(weighted, torch.ones_like(weighted), valid)
        return loss, element_mean(values, entry_valid, steps), element_mean(entry_weights, entry_valid, steps)

    def _entries(self, out, key, tensordict, valid: Tensor, signal: Tensor | None) -> tuple[Tensor, Tensor]:
        """What the weighting weighs and their mask: the per-step losses ``[B, L]`` (event dims reduced) and
        ``valid``; for an element weighting, the per-element losses ``[B, L, *event, A]`` and the mask of their
        valid elements on valid steps (a ranking signal, one value per step, is refused)."""
        if not self.weighting.elementwise:
            return self._step_losses(out, key, tensordict), valid
        event_key, name = self.tensor_keys.event_valid, self.weighting.name
        if signal is not None:
            raise ValueError(
                f"objective {name!r} scores per-element losses, but the inner loss gives a ranking signal "
                f"{self.tensor_keys.signal!r} of one value per step: rank by the loss (no signal) with it."
            )
        elements, event_valid = inner_output.element_losses(out, key, tensordict, event_key, name)
        return elements, event_valid & valid.reshape(valid.shape + (1,) * (elements.ndim - valid.ndim))

    def _step_losses(self, out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase) -> Tensor:
        """The inner per-step loss at ``key`` as ``[B, L]``, event dims reduced (over ``event_valid``'s entries)."""
        return inner_output.step_losses(out, key, tensordict, self.tensor_keys.event_valid)

    def _weight_function(self, device: torch.device):
        """The weighting's function, compiled where ``compile_weights`` says so."""
        spec = self.weighting
        if spec.eager or not compiles_weights(self.compile_weights, device):
            return spec.weights
        if self._compiled_weights is None:
            self._compiled_weights = torch.compile(spec.weights, dynamic=False)
        return self._compiled_weights


def _checked_params(spec: Weighting, params):
    """``params`` for the weighting ``spec`` (its class's defaults for ``None``), refused if of another class."""
    if params is None:
        return spec.params()
    if type(params) is not spec.params:
        raise TypeError(
            f"the {spec.name} weighting takes {spec.params.__name__} parameters "
            f"({', '.join(spec.params.__dataclass_fields__) or 'none'}), got {type(params).__name__}."
        )
    return params


def _check_supervision(spec: Weighting, inner) -> None:
    """Refuse a perturbation control whose inner loss is not a :class:`PerturbedTarget` of its kind: its weights
    alone are the uniform mean."""
    which = inner.which if isinstance(inner, PerturbedTarget) else None
    if spec.perturb is None or spec.perturb == which:
        return
    raise ValueError(
        f"the {spec.name} weighting trains on a corrupted target: wrap the inner loss as "
        f"PerturbedTarget(inner, {spec.perturb!r}, PerturbParams(...)) (tar_rl.recipes.make_objective does), "
        f"got {type(inner).__name__}" + (f" ({which})." if which else ".")
    )


def _check_arguments(inner, schedule, compile_weights: str, nonfinite: str) -> None:
    """Refuse an inner loss that is not an unreduced ``LossModule``, and the other arguments out of range."""
    if not isinstance(inner, LossModule):
        raise TypeError(f"inner must be a torchrl LossModule, got {type(inner).__name__}.")
    reduction = getattr(inner, "reduction", "none")
    if reduction != "none":
        raise ValueError(
            f"TARLoss needs unreduced per-step losses, but the inner {type(inner).__name__} has "
            f"reduction={reduction!r}: build it with reduction='none'."
        )
    if compile_weights not in COMPILE_MODES:
        raise ValueError(f"compile_weights must be one of {list(COMPILE_MODES)}, got {compile_weights!r}.")
    if nonfinite not in NONFINITE_MODES:
        raise ValueError(f"nonfinite must be one of {list(NONFINITE_MODES)}, got {nonfinite!r}.")
    if schedule is not None and not isinstance(schedule, MixSchedule):
        raise TypeError(f"schedule must be a MixSchedule, got {type(schedule).__name__}.")
