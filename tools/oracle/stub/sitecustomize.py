"""Oracle stub for the AMULED authors' scripts: no LLM call can leave this process.

Put this folder first on PYTHONPATH and set ``ORACLE_STUB=1``; nothing happens otherwise.
It never edits the authors' files. It does two things:

1. **The LLM client raises.** Every request method of LangChain's chat models
   (``BaseChatModel.invoke/ainvoke/stream/astream/batch/abatch/generate/agenerate``)
   and of the OpenAI client (``SyncAPIClient.request``, ``AsyncAPIClient.request``)
   raises :class:`OracleLLMCallError`, so a state missing from the cache can never be
   answered by a live model. ``ChatOpenAI`` is still constructed by their script (it
   only stores settings); nothing else of theirs is replaced.

2. **A cache miss** (``ORACLE_ON_MISS``):

   - ``error``: what ``finetune_moral.py`` does with no LLM reachable: its miss branch
     (lines 186-203) calls ``call_llm_with_state_action`` -> ``model.invoke`` -> raises,
     and the run stops at the first state missing from the cache.
   - ``zero`` (default): the rule of their own cache-only variant of the same loop,
     ``kl_sensitivity.py:154-163`` (``RLHF_reward = 0.0  # fallback for uncached
     states``), which our ``miss_policy = "zero"`` follows. ``llm_moral.
     call_llm_with_state_action`` is wrapped (after ``llm_moral`` is imported, before
     ``finetune_moral`` binds the name) so that instead of calling the client it returns
     all-zero beliefs; their ``belief_to_reward`` maps equal rows to those rows
     (``dempster_shafer.py``: ``np.isclose(belief_matrix, belief_matrix[0]).all()``),
     so the step's feedback is 0 for every action, as in ``kl_sensitivity.py``. Their
     script then stores that entry in its (copied) cache, so a later visit also rewards 0.

   Every miss is appended to ``oracle_misses.jsonl`` in the working directory (the
   state's text and time). ``finetune_moral_human.py`` never calls the LLM (its own
   miss rule, ``else: RLHF_reward = 0``, stays as it is).
"""

from __future__ import annotations

import os

if os.environ.get("ORACLE_STUB") == "1":
    import importlib.abc
    import importlib.machinery
    import json
    import sys
    import time

    class OracleLLMCallError(RuntimeError):
        """An LLM call was attempted under the oracle stub (every state must be cached)."""

    def _refuse(*_args, **_kwargs):
        raise OracleLLMCallError(
            "oracle stub: an LLM call was attempted; every state must come from the "
            "authors' cache (ORACLE_ON_MISS=error stops here at the first miss)"
        )

    async def _arefuse(*_args, **_kwargs):
        _refuse()

    def _stub_langchain(module):
        cls = getattr(module, "BaseChatModel", None)
        if cls is None:
            return
        for name in (
            "invoke",
            "stream",
            "batch",
            "generate",
            "generate_prompt",
            "predict",
            "predict_messages",
            "__call__",
            "call_as_llm",
        ):
            if hasattr(cls, name):
                setattr(cls, name, _refuse)
        for name in (
            "ainvoke",
            "astream",
            "abatch",
            "agenerate",
            "agenerate_prompt",
            "apredict",
            "apredict_messages",
        ):
            if hasattr(cls, name):
                setattr(cls, name, _arefuse)

    def _stub_openai(module):
        for cls_name, fn in (("SyncAPIClient", _refuse), ("AsyncAPIClient", _arefuse)):
            cls = getattr(module, cls_name, None)
            if cls is not None:
                cls.request = fn

    def _log_miss(state_text):
        with open("oracle_misses.jsonl", "a") as handle:
            handle.write(json.dumps({"time": time.time(), "state": state_text}) + "\n")

    def _stub_llm_moral(module):
        original = module.call_llm_with_state_action
        mode = os.environ.get("ORACLE_ON_MISS", "zero")
        if mode not in ("zero", "error"):
            raise SystemExit(f"ORACLE_ON_MISS must be zero or error, not {mode!r}")

        def call_llm_with_state_action(
            scenario_prompt, actionsets, state, action, credences, model, final_prompt
        ):
            _log_miss(state)
            if mode == "error":
                return original(
                    scenario_prompt, actionsets, state, action, credences, model, final_prompt
                )  # -> model.invoke -> OracleLLMCallError
            import numpy as np

            beliefs = {agent: np.zeros(len(actionsets)) for agent in credences}
            return beliefs, {}, 0, True

        module.call_llm_with_state_action = call_llm_with_state_action

    _PATCHES = {
        "langchain_core.language_models.chat_models": _stub_langchain,
        "openai._base_client": _stub_openai,
        "llm_moral": _stub_llm_moral,
    }

    class _PatchAfterImport(importlib.abc.MetaPathFinder):
        """Runs a patch right after one of the modules in ``_PATCHES`` is executed."""

        def find_spec(self, fullname, path, target=None):
            if fullname not in _PATCHES:
                return None
            spec = importlib.machinery.PathFinder.find_spec(fullname, path)
            if spec is None or spec.loader is None:
                return spec
            loader = spec.loader
            exec_module = loader.exec_module

            def exec_and_patch(module, _exec=exec_module, _patch=_PATCHES[fullname]):
                _exec(module)
                _patch(module)

            loader.exec_module = exec_and_patch
            return spec

    if os.environ.get("ORACLE_GRADLOG") == "1":
        # Diagnostic only (off by default): record, at each of their
        # ``clip_grad_norm_(agent.parameters(), max_grad_norm)`` calls, the gradient norm of
        # the critic (their Agent registers ``critic`` first: the first 6 tensors) and of
        # the actor (the last 6), before clipping. Nothing is changed: the original
        # function runs on the same parameters and its result is returned.
        import torch.nn.utils as _nn_utils

        _clip = _nn_utils.clip_grad_norm_

        def clip_grad_norm_(parameters, max_norm, *args, **kwargs):
            """Log the critic's and the actor's gradient norm, then clip as before."""
            params = list(parameters)
            if len(params) == 12:
                norms = [float(p.grad.norm()) if p.grad is not None else 0.0 for p in params]
                critic = sum(n * n for n in norms[:6]) ** 0.5
                actor = sum(n * n for n in norms[6:]) ** 0.5
                with open("oracle_gradnorms.csv", "a") as handle:
                    handle.write(f"{critic:.6g},{actor:.6g},{max_norm}\n")
            return _clip(params, max_norm, *args, **kwargs)

        _nn_utils.clip_grad_norm_ = clip_grad_norm_

    sys.meta_path.insert(0, _PatchAfterImport())
    os.environ.setdefault("ORACLE_STUB_ACTIVE", "1")
