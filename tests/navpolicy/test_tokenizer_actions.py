"""Offline tokenizer (Qwen special tokens) and the action <-> token codec."""

from __future__ import annotations

import pytest
from image2sim.navpolicy.actions import (
    ACTION_TEXT,
    ActionCodec,
    ActionCodecError,
    action_text,
    actions_to_text,
    parse_actions,
)
from image2sim.navpolicy.tokenizer import (
    QWEN_SPECIAL_TOKENS,
    build_tiny_tokenizer,
    check_special_tokens,
    load_tokenizer,
)
from image2sim.simulator.conventions import Action


@pytest.fixture(scope="module")
def tok():
    return build_tiny_tokenizer()


def test_action_ids_come_from_conventions():
    assert [int(a) for a in Action] == [0, 1, 2, 3]
    assert actions_to_text([1, 2, 3, 0]) == "FORWARD LEFT RIGHT STOP"
    with pytest.raises(ValueError, match="unknown action id 7"):
        action_text(7)


def test_special_tokens_are_single_and_first(tok):
    ids = check_special_tokens(tok)
    assert list(ids) == list(QWEN_SPECIAL_TOKENS)
    assert list(ids.values()) == list(range(len(QWEN_SPECIAL_TOKENS)))
    assert tok.eos_token == "<|im_end|>" and tok.pad_token == "<|endoftext|>"
    text = "<|im_start|>user\n<|vision_start|><|image_pad|><|image_pad|><|vision_end|><|im_end|>"
    enc = tok(text, add_special_tokens=False)["input_ids"]
    assert enc.count(ids["<|image_pad|>"]) == 2
    assert enc[0] == ids["<|im_start|>"] and enc[-1] == ids["<|im_end|>"]
    assert tok.decode(enc) == text


def test_tiny_tokenizer_is_deterministic_and_roundtrips(tok):
    other = build_tiny_tokenizer()
    s = "Instruction: walk past the sofa, then stop by the door. 0.25 m ünïcode ✓"
    assert tok(s)["input_ids"] == other(s)["input_ids"]
    assert tok.decode(tok(s, add_special_tokens=False)["input_ids"]) == s


def test_actions_are_single_tokens_in_both_positions(tok):
    codec = ActionCodec.from_tokenizer(tok)
    assert codec.single_token
    all_ids = [seq[0] for seq in (*codec.first.values(), *codec.following.values())]
    assert len(set(all_ids)) == 8  # distinct for every action and position
    for a in Action:
        for b in Action:
            joined = tok(f"{ACTION_TEXT[a]} {ACTION_TEXT[b]}", add_special_tokens=False)["input_ids"]
            assert joined == [codec.first[a][0], codec.following[b][0]]
            assert parse_actions(tok.decode(joined)) == [a, b]


def test_codec_handles_multi_token_actions():
    # A tokenizer without the action words as added tokens splits them into several BPE pieces.
    from image2sim.navpolicy import tokenizer as tk

    base = build_tiny_tokenizer(action_texts={})
    codec = ActionCodec.from_tokenizer(base)
    assert not codec.single_token
    for pos in (0, 1):
        table = codec.table(pos)
        for a, seq in table.items():
            # Walking the trie along the sequence reaches exactly this action, and never earlier.
            for k in range(len(seq)):
                assert seq[k] in codec.allowed_next(pos, seq[:k])
                assert codec.match(pos, seq[:k]) is None
            assert codec.match(pos, seq) == a
    assert codec.allowed_next(0, []) == sorted({s[0] for s in codec.first.values()})
    assert tk.QWEN_SPECIAL_TOKENS  # module import sanity


def test_codec_excluded_actions_are_unreachable():
    # Walking the trie without STOP reaches every other action and never STOP (multi-token words, so
    # the exclusion must prune shared prefixes only where they lead to STOP alone).
    codec = ActionCodec.from_tokenizer(build_tiny_tokenizer(action_texts={}))
    for pos in (0, 1):

        def reachable(prefix, pos=pos):
            done = codec.match(pos, prefix)
            if done is not None:
                return {done}
            nxt = codec.allowed_next(pos, prefix, exclude=(Action.STOP,))
            return set().union(*(reachable([*prefix, t]) for t in nxt)) if nxt else set()

        assert reachable([]) == set(Action) - {Action.STOP}
        assert codec.allowed_next(pos, [], exclude=()) == codec.allowed_next(pos, [])


def test_codec_rejects_ambiguous_vocabulary(tok):
    texts = dict(ACTION_TEXT)
    texts[Action.TURN_RIGHT] = "LEFTX"  # "LEFT" + "X": LEFT is a prefix of it
    with pytest.raises(ActionCodecError):
        ActionCodec.from_tokenizer(build_tiny_tokenizer(action_texts={}), texts)
    with pytest.raises(ActionCodecError, match="lack"):
        ActionCodec.from_tokenizer(tok, {Action.STOP: "STOP"})


def test_parse_actions_skips_noise_and_accepts_enum_names():
    assert parse_actions("I think: FORWARD, then TURN_LEFT!") == [Action.MOVE_FORWARD, Action.TURN_LEFT]
    assert parse_actions("forward left") == []  # case-sensitive: instruction words never count
    assert parse_actions("") == []


def test_saved_tokenizer_reloads_from_a_local_folder_only(tok, tmp_path):
    tok.save_pretrained(tmp_path)
    again = load_tokenizer(tmp_path)
    s = "<|im_start|>assistant\nFORWARD LEFT<|im_end|>"
    assert again(s)["input_ids"] == tok(s)["input_ids"]
    with pytest.raises(FileNotFoundError, match="hub ids"):
        load_tokenizer("Qwen/Qwen3-VL-4B-Instruct")


def test_instruction_corpus_makes_the_task_words_whole_tokens(tok):
    """``extra_corpus`` (``model.tiny.tokenizer_corpus: instructions``): the task's words become
    single tokens; the special tokens keep ids 0..6 and every action stays one token."""
    corpus = [f"Walk past the {w} and stop next to the toilet." for w in ("bookshelf", "vase", "armchair")]
    words = (" toilet", " bookshelf", " vase", " armchair")
    assert all(len(tok(w)["input_ids"]) > 1 for w in words)  # the built-in corpus splits them
    task = build_tiny_tokenizer(768, extra_corpus=corpus)
    assert all(len(task(w)["input_ids"]) == 1 for w in words)
    check_special_tokens(task)
    assert ActionCodec.from_tokenizer(task).single_token
    assert task.decode(task("stop next to the vase")["input_ids"]) == "stop next to the vase"
    # Deterministic: the same corpus gives the same vocabulary (a resumed run rebuilds it).
    assert build_tiny_tokenizer(768, extra_corpus=corpus).get_vocab() == task.get_vocab()
