"""TEST-ONLY shim: tiny sizes for LeRobot's pi0 and pi0.5 (never on the product's path).

Loaded by Python at start-up only when a test puts this folder on ``PYTHONPATH`` (``tests/policies/
test_lerobot06_pi.py`` does so for LeRobot 0.6's venv, through a wrapper it passes as ``python=``). LeRobot fixes
pi0's and pi0.5's sizes in code, not in the checkpoint's config: ``get_gemma_config`` knows only ``gemma_300m`` and
``gemma_2b`` (the config names one of them), and ``PaliGemmaWithExpertModel`` takes the SigLIP tower from
transformers' PaliGemma defaults and sets its MLP width (4304), its projection (2048) and the vocabulary (257152).
When ``lerobot.policies.pi0.modeling_pi0`` or ``lerobot.policies.pi05.modeling_pi05`` is imported, this replaces
sizes only, in that module's namespace: the two variant names' widths, depths and heads (:data:`TINY_GEMMA`), and
just before the PaliGemma and expert models are built, the vision tower's width, depth, heads, MLP width and patch
size, the projection (set to the language model's width, as PaliGemma requires) and the vocabulary
(:data:`TINY_VISION`, :data:`TINY_VOCAB`). To do so it rebinds three names in that module: ``get_gemma_config``,
and ``PaliGemmaForConditionalGenerationWithPiGemma`` and ``PiGemmaForCausalLM`` to functions that change those
sizes in the config they are given and call LeRobot's classes. Every class, forward pass, processor and LeRobot's
RTC stay LeRobot's.
Without this shim LeRobot builds the full sizes (about 4e9 parameters) and cannot load a checkpoint made with it.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys

#: Widths for LeRobot's two variant names. Both share depth, heads and head size, as LeRobot's joint attention over
#: the PaliGemma and expert layers requires (so do the real 2B and 300M).
TINY_GEMMA = {
    "gemma_2b": {"width": 64, "depth": 2, "mlp_dim": 128, "num_heads": 2, "num_kv_heads": 1, "head_dim": 16},
    "gemma_300m": {"width": 32, "depth": 2, "mlp_dim": 64, "num_heads": 2, "num_kv_heads": 1, "head_dim": 16},
}
#: SigLIP tower sizes (transformers' PaliGemma default: 1152 wide, 27 layers, 16 heads, MLP 4304, 14 px patches).
TINY_VISION = {"hidden_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2, "intermediate_size": 64,
               "patch_size": 32}  # fmt: skip
#: Vocabulary rows (LeRobot: 257152, PaliGemma's); the test's toy tokenizer has fewer tokens (words and 0..255).
TINY_VOCAB = 512
MODULES = ("lerobot.policies.pi0.modeling_pi0", "lerobot.policies.pi05.modeling_pi05")


def shrink(module) -> None:
    """Replace the sizes in one of LeRobot's pi modules (see the module docstring)."""
    gemma_config, paligemma_class, expert_class = (
        module.GemmaConfig, module.PaliGemmaForConditionalGenerationWithPiGemma, module.PiGemmaForCausalLM,
    )  # fmt: skip

    def get_gemma_config(variant: str):
        if variant not in TINY_GEMMA:
            raise ValueError(f"Unknown variant: {variant}")
        return gemma_config(**TINY_GEMMA[variant])

    def paligemma(config):
        for name, value in TINY_VISION.items():
            setattr(config.vision_config, name, value)
        config.vision_config.projection_dim = config.text_config.hidden_size
        config.text_config.vocab_size = config._vocab_size = TINY_VOCAB  # noqa: SLF001 - LeRobot sets it so
        config.image_token_index = TINY_VOCAB - 1
        return paligemma_class(config=config)

    def expert(config):
        config.vocab_size = TINY_VOCAB
        return expert_class(config=config)

    module.get_gemma_config = get_gemma_config
    module.PaliGemmaForConditionalGenerationWithPiGemma = paligemma
    module.PiGemmaForCausalLM = expert
    module.TINY_SIZES_SHIM = __file__


class _ShrinkingLoader(importlib.abc.Loader):
    """LeRobot's own loader for the module, then :func:`shrink`."""

    def __init__(self, loader: importlib.abc.Loader) -> None:
        self.loader = loader

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module) -> None:
        self.loader.exec_module(module)
        shrink(module)


class _ShrinkAfterImport(importlib.abc.MetaPathFinder):
    """Finds LeRobot's pi modules with the normal finders and hands them to :class:`_ShrinkingLoader`."""

    def find_spec(self, fullname, path, target=None):
        if fullname not in MODULES:
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is not None:
            spec.loader = _ShrinkingLoader(spec.loader)
        return spec


sys.meta_path.insert(0, _ShrinkAfterImport())
