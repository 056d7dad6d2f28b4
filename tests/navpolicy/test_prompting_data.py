"""Prompt layout, label masking, sample construction and the shard format."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from image2sim.navpolicy.collate import NavCollator
from image2sim.navpolicy.data import (
    InMemoryNavDataset,
    NavShardDataset,
    ShardError,
    ShardReader,
    Trajectory,
    make_sample,
    next_actions,
    synthetic_trajectories,
    uniform_indices,
    write_shard,
)
from image2sim.navpolicy.prompting import IGNORE_INDEX, PromptBuilder, Turn
from image2sim.simulator.conventions import Action


@pytest.fixture(scope="module")
def builder(tiny_policy, tiny_cfg):
    return PromptBuilder(tiny_policy.tokenizer, tiny_policy.codec, tiny_cfg.system_prompt)


def _labelled_positions_by_scanning(ids: list[int], tok) -> list[int]:
    """Reference: the two tokens right after each ``<|im_start|>assistant\\n`` that precede ``<|im_end|>``."""
    head = tok("<|im_start|>assistant\n", add_special_tokens=False)["input_ids"]
    im_end = tok.convert_tokens_to_ids("<|im_end|>")
    out = []
    for i in range(len(ids) - len(head)):
        if ids[i : i + len(head)] == head:
            j = i + len(head)
            k = j
            while k < len(ids) and ids[k] != im_end:
                k += 1
            out.extend(range(j, k))
    return out


def test_prompt_text_layout(builder, tiny_policy):
    turns = [
        Turn(frame_key=0, num_image_tokens=3, executed=(), target=(1, 1)),
        Turn(frame_key=4, num_image_tokens=3, executed=(1, 1, 2, 3), target=(2, 0)),
    ]
    enc = builder.encode("go to the sofa", turns)
    text = tiny_policy.tokenizer.decode(enc.input_ids)
    pad = "<|image_pad|>" * 3
    assert text.endswith(
        "Instruction: go to the sofa<|im_end|>\n"
        f"<|im_start|>user\n<|vision_start|>{pad}<|vision_end|><|im_end|>\n"
        "<|im_start|>assistant\nFORWARD FORWARD<|im_end|>\n"
        "<|im_start|>user\nExecuted: FORWARD FORWARD LEFT RIGHT\n"
        f"<|vision_start|>{pad}<|vision_end|><|im_end|>\n"
        "<|im_start|>assistant\nLEFT STOP<|im_end|>\n"
    )
    assert text.startswith("<|im_start|>system\nYou are a navigation agent")
    # Labels: exactly the action tokens, with the token ids themselves (the model shifts internally).
    lab = [i for i, v in enumerate(enc.labels) if v != IGNORE_INDEX]
    assert lab == _labelled_positions_by_scanning(enc.input_ids, tiny_policy.tokenizer)
    assert len(lab) == 4
    assert [enc.input_ids[i] for i in lab] == [enc.labels[i] for i in lab]
    assert tiny_policy.tokenizer.decode([enc.input_ids[i] for i in lab]) == "FORWARD FORWARDLEFT STOP"


def test_generation_prompt_and_bad_turns(builder):
    gen = builder.encode("x", [Turn(0, 2, (), (1, 2)), Turn(1, 2, (1, 2), None)], add_generation_prompt=True)
    assert builder.tokenizer.decode(gen.input_ids).endswith("<|im_end|>\n<|im_start|>assistant\n")
    assert sum(v != IGNORE_INDEX for v in gen.labels) == 2
    with pytest.raises(ValueError, match="no target"):
        builder.encode("x", [Turn(0, 2, (), None), Turn(1, 2, (), (1, 1))])
    with pytest.raises(ValueError, match="must not have a target"):
        builder.encode("x", [Turn(0, 2, (), (1, 1))], add_generation_prompt=True)
    with pytest.raises(ValueError, match="2 actions"):
        builder.encode("x", [Turn(0, 2, (), (1,))])
    with pytest.raises(ValueError, match="at least one"):
        builder.encode("x", [])


@given(n=st.integers(0, 300), k=st.integers(0, 40), seed=st.one_of(st.none(), st.integers(0, 10)))
def test_uniform_indices(n, k, seed):
    rng = None if seed is None else np.random.default_rng(seed)
    idx = uniform_indices(n, k, rng)
    assert len(idx) == min(n, k) if (n > 0 and k > 0) else idx == []
    assert idx == sorted(set(idx)) and all(0 <= i < n for i in idx)
    if idx:
        assert idx[0] == 0
    if n > k > 1:
        # One index per bin of width n/k: spread over the whole trajectory.
        bins = [int(i * k // n) for i in idx]
        assert bins == list(range(k)) or rng is None
        assert max(idx) >= (k - 1) * n // k - 1


def test_make_sample_pairs_observations_with_next_two_actions():
    rng = np.random.default_rng(0)
    T = 100
    acts = [int(a) for a in rng.integers(1, 4, size=T - 1)] + [0]
    frames = rng.integers(0, 255, size=(T, 4, 4, 3), dtype=np.uint8)
    traj = Trajectory("i", acts, frames, list(range(T)))
    s = make_sample(traj, 32, 64, rng)
    assert len(s.steps) == 32 and s.num_labels == 64
    for j, t in enumerate(s.steps):
        assert np.array_equal(s.observations[j], frames[t])
        assert s.targets[j] == (acts[t], acts[t + 1] if t + 1 < T else 0)
        if j:
            assert list(s.executed[j]) == acts[s.steps[j - 1] : t]
    assert s.executed[0] == ()
    # Fewer labels than 2 per observation limit the observation count.
    assert len(make_sample(traj, 32, 10).steps) == 5
    # Short trajectory: every frame, STOP padding past the end.
    short = Trajectory("i", [1, 0], frames[:2], [0, 1])
    s2 = make_sample(short)
    assert s2.steps == [0, 1] and s2.targets == [(1, 0), (0, 0)]
    assert next_actions([1, 2, 3], 2, 3) == (3, int(Action.STOP), int(Action.STOP))


def test_observation_stride_matches_the_streaming_agents_view():
    """With stride 2 a short trajectory is observed every two actions, as the agent observes it:
    steps 0, 2, 4, ..., ``Executed:`` lists of two, targets the next two actions."""
    rng = np.random.default_rng(1)
    T = 15
    acts = [int(a) for a in rng.integers(1, 4, size=T - 1)] + [0]
    frames = rng.integers(0, 255, size=(T, 4, 4, 3), dtype=np.uint8)
    traj = Trajectory("i", acts, frames, list(range(T)))
    s = make_sample(traj, 16, 32, rng, stride=2)
    assert s.steps == list(range(0, T, 2))
    assert all(s.executed[j] == tuple(acts[2 * j - 2 : 2 * j]) for j in range(1, len(s.steps)))
    assert s.targets[-1] == (0, 0) and s.targets[0] == (acts[0], acts[1])
    # Long trajectories: uniform over the even steps only, always starting at step 0.
    long = Trajectory(
        "i", [1] * 99 + [0], rng.integers(0, 255, (100, 4, 4, 3), dtype=np.uint8), list(range(100))
    )
    for seed in range(5):
        st2 = make_sample(long, 8, 16, np.random.default_rng(seed), stride=2).steps
        assert len(st2) == 8 and st2[0] == 0 and all(t % 2 == 0 for t in st2)
    # Frame steps that are not every step: the stride applies to steps, not frame indices.
    sparse = Trajectory("i", [1] * 9 + [0], frames[:4], [0, 3, 6, 8])
    assert make_sample(sparse, 8, 16, stride=2).steps == [0, 6, 8]
    with pytest.raises(ValueError, match="stride"):
        make_sample(traj, stride=0)


def test_collator_masks_everything_but_action_tokens(tiny_policy, builder):
    trajs = synthetic_trajectories(3, min_len=5, max_len=70, seed=1)
    samples = [make_sample(t, 32, 64, np.random.default_rng(i)) for i, t in enumerate(trajs)]
    batch = NavCollator(builder, tiny_policy.image_processor)(samples)
    ids, labels, mm, attn = (
        batch["input_ids"],
        batch["labels"],
        batch["mm_token_type_ids"],
        batch["attention_mask"],
    )
    n_images = sum(len(s.steps) for s in samples)
    assert batch["image_grid_thw"].shape == (n_images, 3)
    assert batch["pixel_values"].shape[0] == int(batch["image_grid_thw"].prod(-1).sum())
    pad_id = tiny_policy.tokenizer.convert_tokens_to_ids("<|image_pad|>")
    assert int((ids == pad_id).sum()) == int(batch["image_grid_thw"].prod(-1).sum()) // 4
    assert bool(((mm == 1) == (ids == pad_id)).all())
    for b, s in enumerate(samples):
        n = int(attn[b].sum())
        assert bool((attn[b, :n] == 1).all()) and bool((attn[b, n:] == 0).all())
        assert bool((labels[b, n:] == IGNORE_INDEX).all())
        expected = _labelled_positions_by_scanning(ids[b, :n].tolist(), tiny_policy.tokenizer)
        got = (labels[b] != IGNORE_INDEX).nonzero().flatten().tolist()
        assert got == expected
        assert len(got) == 2 * len(s.steps) <= 64 and len(s.steps) <= 32
        codec = tiny_policy.codec
        want = [tok for tgt in s.targets for piece in codec.encode(tgt) for tok in piece]
        assert labels[b, got].tolist() == want
    assert bool((labels[mm != 0] == IGNORE_INDEX).all())


def test_shard_roundtrip_and_dataset(tmp_path):
    trajs = synthetic_trajectories(4, min_len=3, max_len=12, height=8, width=12, seed=2)
    trajs[1].frames = trajs[1].frames[::2]
    trajs[1].frame_steps = trajs[1].frame_steps[::2]
    root = write_shard(tmp_path / "shard-0", trajs, observation={"camera": "pinhole", "hfov_deg": 90})
    manifest = json.loads((root / "manifest.json").read_text())
    assert manifest["format"] == "image2sim-navshard" and manifest["num_trajectories"] == 4
    reader = ShardReader(root)
    for a, b in zip(trajs, (reader[i] for i in range(len(reader))), strict=True):
        assert a.actions == b.actions and a.frame_steps == b.frame_steps and a.instruction == b.instruction
        assert np.array_equal(a.frames, b.frames)
    ds = NavShardDataset([root, root], max_observations=4, max_action_labels=8, seed=3)
    assert len(ds) == 8
    s1, s2 = ds[5], ds[5]
    assert s1.steps == s2.steps  # reproducible per (seed, epoch, index)
    assert set(s1.steps) <= set(reader[1].frame_steps)
    mem = InMemoryNavDataset(trajs, 4, 8, seed=3)
    assert mem[1].steps == ds[1].steps


def test_shard_errors_name_the_file(tmp_path):
    with pytest.raises(ShardError, match="manifest.json"):
        ShardReader(tmp_path)
    good = synthetic_trajectories(1, 3, 3, 4, 4)[0]
    bad = Trajectory("i", [1, 9], good.frames[:2], [0, 1])
    with pytest.raises(ShardError, match="unknown action ids"):
        write_shard(tmp_path / "bad", [bad])
    bad2 = Trajectory("i", [1, 0], good.frames[:2], [1, 0])
    with pytest.raises(ShardError, match="increase"):
        bad2.validate()
    root = write_shard(tmp_path / "ok", [good])
    (root / "frames" / "000000.npz").write_bytes(b"garbage")
    with pytest.raises(ShardError, match="000000.npz"):
        ShardReader(root)[0]
    m = json.loads((root / "manifest.json").read_text())
    m["version"] = 99
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ShardError, match="v99"):
        ShardReader(root)


def test_dataengine_shard_writer_output_is_readable(tmp_path, tiny_policy, builder):
    """Contract: shards written by the data engine's own writer load and collate here."""
    shards = pytest.importorskip("image2sim.dataengine.shards")
    trajs = synthetic_trajectories(3, min_len=4, max_len=9, height=16, width=16, seed=11)
    w = shards.SceneShardWriter(tmp_path / "scene-a", observation={"camera": "pinhole"})
    for t in trajs:
        w.add(t.episode_id, t.scene_id, t.instruction, t.actions, t.frames, t.frame_steps, extra={"k": 1})
    root = w.close()
    reader = ShardReader(root)
    assert len(reader) == 3 and reader[2].extra == {"k": 1}
    assert reader[1].actions == trajs[1].actions and np.array_equal(reader[1].frames, trajs[1].frames)
    ds = NavShardDataset([root], max_observations=4, max_action_labels=8)
    batch = NavCollator(builder, tiny_policy.image_processor)([ds[0], ds[1]])
    assert int((batch["labels"] != IGNORE_INDEX).sum()) == 2 * (len(ds[0].steps) + len(ds[1].steps))


def _long_trajectory(T: int = 100, seed: int = 3) -> Trajectory:
    rng = np.random.default_rng(seed)
    acts = [int(a) for a in rng.integers(1, 4, size=T - 1)] + [int(Action.STOP)]
    return Trajectory("long", acts, rng.integers(0, 255, (T, 4, 4, 3), dtype=np.uint8), list(range(T)))


def test_streaming_samples_are_what_the_agent_sees_at_the_cut():
    """``context=(sparse, dense)``: a sample is the agent's context after ``cut + 1`` observations
    (one per two actions), labelled with the oracle's next two actions at every frame."""
    from image2sim.navpolicy.data import select_context_frames

    traj = _long_trajectory()
    seen_cuts = set()
    for seed in range(40):
        s = make_sample(traj, 16, 32, np.random.default_rng(seed), stride=2, context=(8, 8))
        obs_index = [t // 2 for t in s.steps]  # the agent's observation k is taken at step 2k
        cut = obs_index[-1]
        seen_cuts.add(cut)
        assert obs_index == select_context_frames(cut + 1, 8, 8)
        assert all(t % 2 == 0 for t in s.steps) and s.steps[0] == 0
        # Executed = every action between consecutive context frames (the agent's history text).
        assert all(
            s.executed[j] == tuple(traj.actions[s.steps[j - 1] : s.steps[j]]) for j in range(1, len(s.steps))
        )
        assert s.targets == [tuple(traj.actions[t : t + 2]) for t in s.steps]
        np.testing.assert_array_equal(s.observations, np.asarray(traj.frames)[s.steps])
    # Cuts are spread over the whole episode, not only its end (where the uniform layout always ends).
    assert min(seen_cuts) < 15 and max(seen_cuts) > 35 and len(seen_cuts) > 20
    # Without rng: the cut is the end, so the last label is the final STOP.
    end = make_sample(traj, 16, 32, None, stride=2, context=(8, 8))
    assert end.steps[-1] == 98 and end.targets[-1] == (int(traj.actions[98]), int(Action.STOP))


def test_streaming_samples_label_stop_only_at_the_end():
    """Uniform layout: every sample ends in the trajectory's last sixteenth, where the full context is
    followed by STOP. Streaming: STOP ends only the samples cut at the end."""
    traj = _long_trajectory()
    stop = int(Action.STOP)
    uni = [make_sample(traj, 16, 32, np.random.default_rng(s), stride=2) for s in range(60)]
    assert all(len(s.steps) == 16 and s.steps[-1] >= 92 for s in uni)
    rngs = [np.random.default_rng(s) for s in range(60)]
    stream = [make_sample(traj, 16, 32, rng, stride=2, context=(8, 8)) for rng in rngs]
    with_stop = sum(stop in s.targets[-1] for s in stream)
    assert with_stop < 10  # 1 of 50 cuts ends the episode: ~1.2 expected in 60 draws


def test_streaming_context_must_fit_the_sample():
    traj = _long_trajectory(20)
    with pytest.raises(ValueError, match="streaming context"):
        make_sample(traj, 8, 16, stride=2, context=(8, 8))
    with pytest.raises(ValueError, match="dense >= 1"):
        make_sample(traj, 16, 32, stride=2, context=(8, 0))


def test_streaming_config_is_validated(tiny_cfg):
    import copy

    from image2sim.navpolicy.config import ConfigError
    from image2sim.navpolicy.data import sample_options

    cfg = copy.deepcopy(tiny_cfg)
    cfg.data.sampling = "streaming"
    cfg.agent.sparse_frames, cfg.agent.dense_frames = 8, 8
    cfg.data.max_observations, cfg.data.max_action_labels = 16, 32
    assert sample_options(cfg.validate())["context"] == (8, 8)
    cfg.agent.sparse_frames = 24
    with pytest.raises(ConfigError, match="sparse_frames"):
        cfg.validate()
    cfg.data.sampling = "random"
    with pytest.raises(ConfigError, match="data.sampling must be one of uniform, streaming"):
        cfg.validate()


def test_end_cut_probability_oversamples_the_final_stop():
    traj = _long_trajectory()
    stop = int(Action.STOP)
    for p, lo, hi in ((0.0, 0, 6), (0.3, 40, 80), (1.0, 200, 200)):
        n = sum(
            stop in make_sample(traj, 16, 32, np.random.default_rng(s), 2, (8, 8), p).targets[-1]
            for s in range(200)
        )
        assert lo <= n <= hi, (p, n)


def test_late_starts_are_the_agents_context_from_a_later_start():
    """``late_start_probability``: the sample is what an agent placed at a later frame would hold at
    the cut (its context selected over the suffix, history text from that start), and the number of
    frames seen no longer predicts a final STOP."""
    from image2sim.navpolicy.data import select_context_frames

    traj = _long_trajectory()
    stop = int(Action.STOP)
    late, stops, seen_counts = 0, [], []
    for seed in range(2000):
        s = make_sample(traj, 16, 32, np.random.default_rng(seed), 2, (8, 8), 0.5, 1.0)
        obs_index = [t // 2 for t in s.steps]
        start, cut = obs_index[0], obs_index[-1]
        late += start > 0
        assert obs_index == [start + i for i in select_context_frames(cut + 1 - start, 8, 8)]
        assert s.executed[0] == ()
        assert all(
            s.executed[j] == tuple(traj.actions[s.steps[j - 1] : s.steps[j]]) for j in range(1, len(s.steps))
        )
        np.testing.assert_array_equal(s.observations, np.asarray(traj.frames)[s.steps])
        stops.append(stop in s.targets[-1])
        seen_counts.append(cut + 1 - start)
    assert late > 1800  # start 0 only when every candidate up to the cut is seen
    stops, seen_counts = np.asarray(stops), np.asarray(seen_counts)
    # 50 candidates; the end is cut half the time, whatever the count seen (but the last count).
    for lo, hi in ((1, 16), (16, 32), (32, 50)):
        sel = (seen_counts >= lo) & (seen_counts < hi)
        assert abs(stops[sel].mean() - 0.5) < 0.08, (lo, hi, stops[sel].mean())
    # Disabled: the sample stream is the one drawn without the option.
    for seed in range(20):
        a = make_sample(traj, 16, 32, np.random.default_rng(seed), 2, (8, 8), 0.25)
        b = make_sample(traj, 16, 32, np.random.default_rng(seed), 2, (8, 8), 0.25, 0.0)
        assert a.steps == b.steps and a.steps[0] == 0


def test_max_trajectories_keeps_the_first_ones_in_shard_order(tmp_path, tiny_cfg):
    import copy

    from image2sim.navpolicy.config import ConfigError

    a = write_shard(tmp_path / "a", synthetic_trajectories(3, height=8, width=8, seed=1))
    b = write_shard(tmp_path / "b", synthetic_trajectories(4, height=8, width=8, seed=2))
    full = NavShardDataset([a, b])
    part = NavShardDataset([a, b], max_trajectories=5)
    assert len(full) == 7 and len(part) == 5 and part.index == full.index[:5]
    with pytest.raises(ValueError, match="max_trajectories"):
        NavShardDataset([a], max_trajectories=0)
    cfg = copy.deepcopy(tiny_cfg)
    cfg.data.shards, cfg.data.shard_weights, cfg.data.max_trajectories = [str(a), str(b)], [1.0, 1.0], 3
    with pytest.raises(ConfigError, match="max_trajectories"):
        cfg.validate()


def test_shuffled_instructions_permute_instructions_and_keep_everything_else(tmp_path):
    """data.shuffle_instructions (the instruction-blind control): every trajectory keeps its actions
    and frames but is told another trajectory's instruction, a fixed seeded permutation."""
    trajs = synthetic_trajectories(12, height=8, width=8, seed=4)
    for k, t in enumerate(trajs):
        t.instruction = f"instruction number {k}"
    root = write_shard(tmp_path / "s", trajs)
    plain = NavShardDataset([root], seed=5)
    mixed = NavShardDataset([root], seed=5, shuffle_instructions=True)
    again = NavShardDataset([root], seed=5, shuffle_instructions=True)
    got = [mixed.trajectory(i) for i in range(len(mixed))]
    ref = [plain.trajectory(i) for i in range(len(plain))]
    assert sorted(t.instruction for t in got) == sorted(t.instruction for t in ref)  # a permutation
    assert sum(a.instruction != b.instruction for a, b in zip(got, ref, strict=True)) >= 8
    assert [t.instruction for t in got] == [again.trajectory(i).instruction for i in range(len(again))]
    for a, b in zip(got, ref, strict=True):
        assert a.actions == b.actions and np.array_equal(a.frames, b.frames)
    # The sample the policy trains on carries the swapped instruction.
    assert mixed[0].instruction == got[0].instruction
