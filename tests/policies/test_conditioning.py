"""Task conditioning (tar_rl.policies.common): the instruction bag of words, by hand."""

from __future__ import annotations

import pytest
import torch

from tar_rl.collectors.metaworld.tasks import INSTRUCTIONS, TASKS
from tar_rl.policies.common import TaskEncoder, instruction_tokens

TEXTS = tuple(INSTRUCTIONS[t] for t in TASKS)  # the instruction of every MetaWorld task id


def test_instruction_tokens_spell_each_sentence():
    ids, mask, vocab = instruction_tokens(len(TASKS), TEXTS)
    words = sorted({w.strip(".,").lower() for s in INSTRUCTIONS.values() for w in s.split()} - {""})
    assert vocab == len(words) + 1
    i = TASKS.index("reach-v3")
    sentence = [w.strip(".,").lower() for w in INSTRUCTIONS["reach-v3"].split()]
    assert [words[j - 1] for j in ids[i][mask[i]].tolist()] == sentence
    assert not mask[i, len(sentence) :].any()


def test_instruction_encoder_is_the_mean_of_word_vectors_projected():
    torch.manual_seed(0)
    enc = TaskEncoder("instruction", len(TASKS), 8, TEXTS)
    ids, mask, _ = instruction_tokens(len(TASKS), TEXTS)
    i = TASKS.index("push-v3")
    mean = enc.words.weight[ids[i][mask[i]]].mean(0)
    expected = enc.project(mean)
    got = enc(torch.tensor([[i, i]]))
    assert got.shape == (1, 2, 8)
    torch.testing.assert_close(got[0, 0], expected)
    got.sum().backward()
    assert enc.words.weight.grad is not None and enc.project.weight.grad is not None


def test_embedding_encoder_and_bad_kind():
    enc = TaskEncoder("embedding", 50, 4)
    torch.testing.assert_close(enc(torch.tensor([3])), enc.embedding.weight[3:4])
    with pytest.raises(ValueError, match="task_conditioning"):
        TaskEncoder("text", 50, 4)


def test_mlp_head_takes_the_instruction_conditioning():
    from tar_rl.policies import DataInfo, build_policy

    torch.manual_seed(0)
    config = {"name": "mlp", "task_conditioning": "instruction", "hidden": [16]}
    policy = build_policy(config, DataInfo(instructions=TEXTS))
    net = policy.actor.module
    assert isinstance(net.task_embedding, TaskEncoder) and net.task_embedding.kind == "instruction"
    obs = torch.zeros(2, 39)
    a = net(obs, torch.tensor([TASKS.index("push-v3"), TASKS.index("reach-v3")]))
    assert a.shape == (2, 4) and not torch.equal(a[0], a[1])  # same observation, different instructions
    a.sum().backward()
    assert net.task_embedding.words.weight.grad.abs().sum() > 0


def test_instruction_conditioning_without_texts_is_refused():
    with pytest.raises(ValueError, match="needs the instruction text of every task id"):
        TaskEncoder("instruction", 3, 4)
    with pytest.raises(ValueError, match=r"task ids \[1\] have no instruction text"):
        TaskEncoder("instruction", 2, 4, ("pick the cup", ""))
