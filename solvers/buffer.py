"""Per-step state buffer with checkpoints, shared by every solver's gradient path.

With `every=None` each step keeps its own input state (fastest backward, memory linear in the
horizon). With `every=K` only every K-th state is kept (a checkpoint); the backward pass asks for
the state of step t, and the buffer replays the window [c, c + K) from its checkpoint c once,
caching the window's states, so each step is recomputed once and memory holds T/K checkpoints plus
one window. States are opaque objects here (the bridge decides what they are).
"""
from typing import Any, Callable, Dict, Optional


class StepBuffer:
    def __init__(self, every: Optional[int], replay: Callable[[Any, int], Any]):
        """replay(state_t, t) -> state_{t+1}, re-running step t with the inputs it had."""
        self.every = every
        self.replay = replay
        self.checkpoints: Dict[int, Any] = {}
        self.window: Dict[int, Any] = {}
        self.n_replayed = 0

    def record(self, t: int, state: Any) -> bool:
        """Offer the input state of step t; returns True if the step itself must keep it (no checkpointing)."""
        if self.every is None:
            return True
        if t % self.every == 0:
            self.checkpoints[t] = state
        return False

    def get(self, t: int) -> Any:
        """The state at step t (recomputed from the nearest checkpoint at or before t when needed)."""
        if t in self.window:
            return self.window[t]
        c = (t // self.every) * self.every
        if c not in self.checkpoints:
            raise KeyError(f"no checkpoint at step {c} for step {t}")
        self.window = {c: self.checkpoints[c]}
        state = self.checkpoints[c]
        for s in range(c, min(c + self.every, t + 1) - 1):
            state = self.replay(state, s)
            self.window[s + 1] = state
            self.n_replayed += 1
        return self.window[t]

    def clear(self):
        self.checkpoints.clear()
        self.window.clear()

    @property
    def n_stored(self) -> int:
        return len(self.checkpoints) + len(self.window)
