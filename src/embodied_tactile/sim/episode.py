"""Consecutive touches on one object (active palpation episodes, docs/reference/active.md).

A touch is one simulated trial (:func:`~embodied_tactile.sim.trial.simulate_trial`): approach
to the preload, 10 s of the primitive, then lift-off. Between two touches the skin leaves the
object and comes back, so contact is *reset*: every touch starts from a fresh approach with
its own placement error (the ``placement`` stream), tracking error, sensor noise and clock
jitter. No state of the skin or the object carries over (the relaxation of the viscoelastic
contact restarts; the lift-off is long compared with the relaxation times of the contact
model). What carries across touches is only the observer's belief (the Latent Filter's state),
which is outside the simulator.

Seed streams: touch ``use`` of action ``action_index`` in episode ``episode_seed`` is the
trial with ``seed = EPISODE_SEED_BASE + episode_seed`` and ``repetition = use`` (how many
times the episode touched with that action before). So

* the touches never coincide with the training data (generated with ``sim_seed`` 0 ..
  ``EPISODE_SEED_BASE - 1``),
* two policies run under the same episode seed receive identical sensor data whenever they
  choose the same action for the same time, which makes policy comparisons paired,
* an episode is a deterministic function of (object, actions chosen, episode seed).
"""

from __future__ import annotations

from embodied_tactile.data.rawformat import RawTrial
from embodied_tactile.sim.physics import PhysicsOverrides
from embodied_tactile.sim.trial import simulate_trial

#: Simulator seeds of episode touches start here (training scenes use small ``sim_seed``).
EPISODE_SEED_BASE = 1_000_000


def touch_seed(episode_seed: int) -> int:
    """The simulator seed of every touch of episode ``episode_seed`` (>= 0)."""
    if int(episode_seed) != episode_seed or episode_seed < 0:
        raise ValueError(f"episode seed must be an integer >= 0, got {episode_seed!r}")
    return EPISODE_SEED_BASE + int(episode_seed)


def simulate_touch(object_id: int, skin: str, primitive: str, action_index: int, use: int, episode_seed: int, *,
                   physics: PhysicsOverrides | None = None) -> RawTrial:
    """One touch of an episode (contact reset before it, see the module docstring): the
    ``use``-th touch with ``action_index`` on ``object_id`` in episode ``episode_seed``."""
    return simulate_trial(object_id, skin, primitive, action_index, repetition=int(use),
                          seed=touch_seed(episode_seed), physics=physics)
