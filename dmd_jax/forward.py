"""The compiled forward passes of a trained DMD-Net, one per model config.

Configs are frozen and hashable, so a config is its own cache key: every `denoise` call
(and every patch of one) with the same config reuses one program object, and XLA
compiles it once per padded shape.

* `predictor`: the whole network on a whole mesh.
* `patch_predictor`: the network on a patch, every per-mesh pool (the transformer's
  `W_tf`, the STN's) given from outside (`DMDNet(pooled=...)`).
* `pool_predictor`: the network up to some pools only, for the patch path's first sweeps.

Each is a `Program`: a jitted function whose compiled executables are kept by input
shapes, in this process and in the on-disk cache of `dmd_jax.compile_cache`, so a new
process on a mesh of a shape bucket seen before loads the executable instead of
tracing, lowering and compiling the network again (`docs/cold-start.md`).
"""

from __future__ import annotations

import threading
import time
from functools import lru_cache

import jax

from dmd_jax import compile_cache
from dmd_jax.config import ExperimentConfig, ModelConfig

# JAX's persistent cache for the other (small) programs of a call: configured here, on
# the import of the first module that compiles the network, never at `import dmd_jax`.
compile_cache.configure_jax()


# `(program name, seconds)` of every program this process compiled (not loaded from the
# on-disk cache): the CLI notes a compile a warm-up would have saved.
COMPILED: list[tuple[str, float]] = []


class Program:
    """A jitted function whose executables are looked up by input signature.

    Calls with the shapes and dtypes of an earlier call run that call's executable;
    a new signature is loaded from the on-disk cache (`compile_cache.executable`) or
    compiled and stored there. With the cache off (`DMD_JAX_COMPILE_CACHE=0`) or
    several devices (patches on several devices, each executable bound to one), calls
    go to `jax.jit` as they are. Either way the same compiled program runs: results are
    bit-identical.

    Args:
      name: the program's kind (part of its cache key).
      fn: the function to jit.
      identity: what else selects the program (its model config, its options).
    """

    def __init__(self, name: str, fn, identity: str):
        self.name = name
        self.jitted = jax.jit(fn)
        self.identity = identity
        self._compiled: dict = {}
        self._loaded: dict = {}
        self._locks: dict = {}
        self._lock = threading.Lock()

    def __call__(self, *args):
        if jax.local_device_count() > 1 or compile_cache.store() is None:
            return self.jitted(*args)
        return self.compiled(*args)(*args)

    def _lock_of(self, sig) -> threading.Lock:
        with self._lock:
            return self._locks.setdefault(sig, threading.Lock())

    def compiled(self, *args):
        """The executable for `args`' signature (arrays or `jax.ShapeDtypeStruct`s)."""
        sig = compile_cache.signature(args)
        found = self._compiled.get(sig)
        if found is None:
            # One compile per signature; others may compile beside it. A `preload` of
            # this signature holds the lock while it loads: waiting for it is quicker
            # than loading again.
            with self._lock_of(sig):
                found = self._compiled.get(sig)
                if found is None:
                    start = time.perf_counter()
                    found, self._loaded[sig] = compile_cache.lookup(
                        self.name, self.jitted, args, self.identity
                    )
                    if not self._loaded[sig]:
                        COMPILED.append((self.name, time.perf_counter() - start))
                    self._compiled[sig] = found
        return found

    def preload(self, *args) -> threading.Thread | None:
        """Starts loading the executable for `args`' signature from the on-disk cache in
        a background thread, to overlap the load with the caller's host work; a later
        call of that signature waits for it instead of loading again.

        A new process loads the whole-mesh program while `inference` checks and
        pre-smooths the mesh: XLA's deserialisation (0.4-0.5 s at 80k faces on 2
        cores) runs mostly outside the GIL. Nothing is compiled here: on a miss (a
        wrong guess of the shapes, a program never warmed up) the thread ends and the
        call compiles as it would have; any error is left to that call too.

        Args:
          args: as for a call (arrays or `jax.ShapeDtypeStruct`s).

        Returns:
          The thread, or None when there is nothing to load (the cache off, several
          devices, the executable already in this process).
        """
        if jax.local_device_count() > 1 or compile_cache.store() is None:
            return None
        sig = compile_cache.signature(args)
        if sig in self._compiled:
            return None
        lock = self._lock_of(sig)
        if not lock.acquire(blocking=False):  # being loaded or compiled already
            return None

        def load():
            try:
                if sig not in self._compiled:
                    found = compile_cache.stored(self.name, args, self.identity)
                    if found is not None:
                        self._loaded[sig] = True
                        self._compiled[sig] = found
            except Exception:  # noqa: BLE001 - only a head start: the call itself reports
                pass
            finally:
                lock.release()

        # Not a daemon: an interpreter that exits meanwhile waits for XLA to finish
        # rather than stopping a thread inside it.
        thread = threading.Thread(target=load, name=f"dmd_jax-preload-{self.name}")
        thread.start()
        return thread

    def prepare(self, *args) -> str:
        """Makes the executable for `args`' signature ready; says how: `"ready"` (this
        process had it), `"loaded"` (from the on-disk cache) or `"compiled"`."""
        sig = compile_cache.signature(args)
        if sig in self._compiled:
            return "ready"
        self.compiled(*args)
        return "loaded" if self._loaded.get(sig) else "compiled"

    def lower(self, *args):
        """`jax.jit(fn).lower(*args)`, whose `.compile()` goes through the cache."""
        return _Lowered(self, args)


class _Lowered:
    """`Program.lower`'s result: `compile()` returns the cached executable."""

    def __init__(self, program: Program, args):
        self._program = program
        self._args = args

    def compile(self):
        return self._program.compiled(*self._args)


def _model_config(config: ExperimentConfig | ModelConfig) -> ModelConfig:
    return config.model if isinstance(config, ExperimentConfig) else config


def predictor(config: ExperimentConfig | ModelConfig) -> Program:
    """`predict(params, noisy, graph) -> [n_vertex, 3]`, compiled, for `config`'s network."""
    return _predictor(_model_config(config))


@lru_cache(maxsize=8)
def _model(config: ModelConfig):
    """The Flax module of `config`, built when a program is first traced: a process that
    loads every executable from the cache never imports Flax (docs/cold-start.md)."""
    from dmd_jax.model import DMDNet

    return DMDNet(config)


@lru_cache(maxsize=8)
def _predictor(config: ModelConfig) -> Program:
    def predict(params, noisy, graph):
        out, _, _ = _model(config).apply({"params": params}, noisy, graph, deterministic=True)
        return out

    return Program("predict", predict, repr(config))


def patch_predictor(config: ExperimentConfig | ModelConfig) -> Program:
    """`predict(params, noisy, graph, pooled) -> [n_vertex, 3]`, compiled: every per-mesh
    pool given (`DMDNet(pooled=...)`)."""
    return _patch_predictor(_model_config(config))


@lru_cache(maxsize=8)
def _patch_predictor(config: ModelConfig) -> Program:
    def predict(params, noisy, graph, pooled):
        out, _, _ = _model(config).apply(
            {"params": params}, noisy, graph, deterministic=True, pooled=pooled
        )
        return out

    return Program("patch", predict, repr(config))


@lru_cache(maxsize=8)
def pool_predictor(config: ModelConfig, names: tuple[str, ...]) -> Program:
    """`pools(params, noisy, graph, pooled) -> {name: pool}`, compiled: the forward pass
    up to the pools `names` (earlier stages' pools given).

    Only the pools are returned, so XLA drops everything that does not feed them (the
    denoiser, the vertex update).
    """

    def pools(params, noisy, graph, pooled):
        _, state = _model(config).apply(
            {"params": params},
            noisy,
            graph,
            deterministic=True,
            pooled=pooled,
            mutable=["intermediates"],
        )
        found = dict(_find_sown(state["intermediates"]))
        return {name: found[name][0] for name in names}  # row 0: the patch's graph

    return Program("pools", pools, repr((config, names)))


def _find_sown(tree):
    """`(name, value)` of every value `Module.sow` recorded, at any depth."""
    for key, value in tree.items():
        if isinstance(value, tuple):
            yield key, value[-1]
        else:
            yield from _find_sown(value)
