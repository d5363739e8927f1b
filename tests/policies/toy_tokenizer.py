"""The word-level toy tokenizer the tiny LeRobot models of the tests are built with (no hub, no download).

Imported by the scripts that run in LeRobot's own venvs (``lerobot_*_script.py``), which put this folder on their
path as the folder of the script itself.
"""

from __future__ import annotations

#: Words of every toy tokenizer: enough for the test prompts (anything else is the unknown token).
TOY_WORDS = "pick up the black bowl and place it on plate between cabinet stove put push open close turn"


def word_level_tokenizer(tokens: list[str], *, max_vocab: int | None = None, **special):
    """A transformers fast tokenizer whose vocabulary is ``tokens`` in order (each once), split on whitespace.

    ``special``: the special tokens by transformers' names (``pad_token="<pad>"``, ``unk_token=...``, ...); the unknown
    token must be in ``tokens``. ``max_vocab``: the tiny model's vocabulary size, which the tokenizer must not exceed
    (SystemExit, naming both, if it does). Returns (tokenizer, vocab: token -> id).
    """
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    vocab = {token: i for i, token in enumerate(dict.fromkeys(tokens))}
    if max_vocab is not None and len(vocab) > max_vocab:
        raise SystemExit(f"the toy tokenizer has {len(vocab)} tokens: more than the tiny model's {max_vocab}")
    word_level = Tokenizer(models.WordLevel(vocab=vocab, unk_token=special["unk_token"]))
    word_level.pre_tokenizer = pre_tokenizers.Whitespace()
    return PreTrainedTokenizerFast(tokenizer_object=word_level, **special), vocab
