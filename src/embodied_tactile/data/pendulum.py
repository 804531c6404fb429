"""Driven, damped pendulum benchmark (Karl et al. 2017, Deep Variational Bayes Filters),
NumPy only (no torch): the data side of ``experiments/pendulum.py`` (docs/reference/model.md,
"Pendulum benchmark").

Dynamics of the angle theta (rad, 0 = bob straight down), with natural frequency w0
(rad/s), damping coefficient d (1/s) and the action u (angular acceleration, rad/s^2):

    theta'' = -w0^2 sin(theta) - d theta' + u

integrated with classical RK4, ``substeps`` substeps per 50 ms frame, u held constant over
a frame. The 8 "objects" are w0 in {2, 3, 4, 5} x d in {0.1, 0.6} (object id =
4 * damping index + frequency index): hidden parameters that only the dynamics reveal, as
the tactile objects' properties. Actions are piecewise constant, a new uniform value in
[-u_max, u_max] every ``hold`` frames. Each frame is a 28x28 image of the bob (a Gaussian
blob of ``blob_sigma`` pixels at radius ``radius`` from the pivot at the image centre) plus
Gaussian pixel noise of standard deviation ``noise``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

FREQUENCIES = (2.0, 3.0, 4.0, 5.0)  # natural frequency w0, rad/s
DAMPINGS = (0.1, 0.6)  # damping coefficient d, 1/s
N_OBJECTS = len(FREQUENCIES) * len(DAMPINGS)
#: systems never seen in training, each parameter strictly between the training grid's
#: values: w0 in {2.5, 3.5, 4.5} x d in {0.25, 0.45} (object id -1: the prior's population
#: marginal)
UNSEEN_SYSTEMS = tuple((w, d) for d in (0.25, 0.45) for w in (2.5, 3.5, 4.5))
DT = 0.05  # s per frame
SIZE = 28  # image side, pixels


def object_params(object_id: int) -> tuple[float, float]:
    """Object id 0..7 -> (w0, d)."""
    if not 0 <= int(object_id) < N_OBJECTS:
        raise ValueError(f"pendulum object_id must be in [0, {N_OBJECTS}), got {object_id}")
    return FREQUENCIES[int(object_id) % len(FREQUENCIES)], DAMPINGS[int(object_id) // len(FREQUENCIES)]


def _accel(theta: np.ndarray, omega: np.ndarray, w0: np.ndarray, d: np.ndarray, u: np.ndarray) -> np.ndarray:
    return -w0 * w0 * np.sin(theta) - d * omega + u


def integrate(theta0: np.ndarray, omega0: np.ndarray, w0: np.ndarray, d: np.ndarray, u: np.ndarray,
              dt: float = DT, substeps: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """RK4 integration of a batch of pendulums.

    theta0, omega0, w0, d: (N,); u: (N, T) the action held over frame t. Returns theta, omega
    (N, T): the state at the start of each frame, i.e. frame 0 is (theta0, omega0) and frame
    t + 1 follows from frame t under u[:, t] (the last action drives past the sequence).
    """
    u = np.asarray(u, dtype=np.float64)
    n, t_len = u.shape
    th = np.asarray(theta0, dtype=np.float64).copy()
    om = np.asarray(omega0, dtype=np.float64).copy()
    w0, d = np.asarray(w0, dtype=np.float64), np.asarray(d, dtype=np.float64)
    h = float(dt) / int(substeps)
    thetas, omegas = np.empty((n, t_len)), np.empty((n, t_len))
    for t in range(t_len):
        thetas[:, t], omegas[:, t] = th, om
        ut = u[:, t]
        for _ in range(int(substeps)):
            k1t, k1o = om, _accel(th, om, w0, d, ut)
            k2t, k2o = om + 0.5 * h * k1o, _accel(th + 0.5 * h * k1t, om + 0.5 * h * k1o, w0, d, ut)
            k3t, k3o = om + 0.5 * h * k2o, _accel(th + 0.5 * h * k2t, om + 0.5 * h * k2o, w0, d, ut)
            k4t, k4o = om + h * k3o, _accel(th + h * k3t, om + h * k3o, w0, d, ut)
            th = th + h / 6.0 * (k1t + 2 * k2t + 2 * k3t + k4t)
            om = om + h / 6.0 * (k1o + 2 * k2o + 2 * k3o + k4o)
    return thetas, omegas


def render(theta: np.ndarray, radius: float = 10.0, blob_sigma: float = 1.5) -> np.ndarray:
    """Angles (...,) -> noiseless images (..., 28, 28) in [0, 1]: the bob at
    (row, col) = (c + r cos theta, c + r sin theta) around the centre c = 13.5."""
    theta = np.asarray(theta, dtype=np.float64)
    c = (SIZE - 1) / 2.0
    rows = c + radius * np.cos(theta)
    cols = c + radius * np.sin(theta)
    grid = np.arange(SIZE, dtype=np.float64)
    gr = np.exp(-0.5 * ((grid - rows[..., None]) / blob_sigma) ** 2)  # (..., 28)
    gc = np.exp(-0.5 * ((grid - cols[..., None]) / blob_sigma) ** 2)
    return gr[..., :, None] * gc[..., None, :]


@dataclass
class PendulumData:
    """A set of pendulum sequences (N sequences of T frames).

    obs (N, T, 1, 28, 28) float32 (noisy images), actions (N, T, 1) float32 (u held over
    frame t), theta, omega (N, T) float64 (state at each frame), object_id (N,) int64,
    w0, damping (N,) float64.
    """

    obs: np.ndarray
    actions: np.ndarray
    theta: np.ndarray
    omega: np.ndarray
    object_id: np.ndarray
    w0: np.ndarray
    damping: np.ndarray

    def __len__(self) -> int:
        return int(self.obs.shape[0])


def generate(n_per_object: int, seed: int, n_steps: int = 60, hold: int = 5, u_max: float = 3.0,
             noise: float = 0.05, substeps: int = 10, omega0_max: float = 2.0,
             systems: Optional[Sequence[tuple[float, float]]] = None) -> PendulumData:
    """``n_per_object`` sequences of each of the 8 objects (object-major order), fully
    determined by ``seed``. Initial angle uniform in [-pi, pi), initial angular velocity
    uniform in [-omega0_max, omega0_max] rad/s. ``systems``: (w0, d) pairs to simulate
    instead of the 8 objects (such as :data:`UNSEEN_SYSTEMS`), each with object id -1."""
    if n_per_object < 1 or n_steps < 1 or hold < 1 or substeps < 1:
        raise ValueError(f"pendulum generate: n_per_object={n_per_object}, n_steps={n_steps}, hold={hold}, "
                         f"substeps={substeps} must all be >= 1")
    rng = np.random.default_rng(seed)
    if systems is None:
        ids = np.repeat(np.arange(N_OBJECTS), n_per_object)
        params = np.array([object_params(i) for i in ids])
    else:
        params = np.repeat(np.asarray(systems, dtype=np.float64).reshape(-1, 2), n_per_object, axis=0)
        if len(params) == 0 or not np.all(params[:, 0] > 0) or not np.all(params[:, 1] >= 0):
            raise ValueError(f"pendulum generate: systems must be (w0 > 0, d >= 0) pairs, got {systems!r}")
        ids = np.full(len(params), -1)
    n = len(ids)
    w0, d = params[:, 0], params[:, 1]
    n_blocks = -(-n_steps // hold)
    u = np.repeat(rng.uniform(-u_max, u_max, size=(n, n_blocks)), hold, axis=1)[:, :n_steps]
    theta0 = rng.uniform(-np.pi, np.pi, size=n)
    omega0 = rng.uniform(-omega0_max, omega0_max, size=n)
    theta, omega = integrate(theta0, omega0, w0, d, u, DT, substeps)
    img = render(theta) + noise * rng.standard_normal((n, n_steps, SIZE, SIZE))
    return PendulumData(obs=img[:, :, None].astype(np.float32), actions=u[..., None].astype(np.float32),
                        theta=theta, omega=omega, object_id=ids.astype(np.int64), w0=w0, damping=d)


def angle_precision(noise: float = 0.05, n_angles: int = 64) -> float:
    """Per-frame angle precision a noisy image allows (rad): the Cramer-Rao bound
    1 / sqrt(I(theta)), I(theta) = sum over pixels of (d image / d theta)^2 / noise^2, the
    image's pixel noise i.i.d. N(0, noise^2); the median over ``n_angles`` angles on the circle
    (the bound varies a little with where the bob sits on the pixel grid)."""
    theta = np.linspace(-np.pi, np.pi, n_angles, endpoint=False)
    h = 1e-5
    grad = (render(theta + h) - render(theta - h)) / (2 * h)
    fisher = (grad ** 2).sum(axis=(-2, -1)) / noise ** 2
    return float(np.median(1.0 / np.sqrt(fisher)))


def parameter_separation(data: PendulumData, parameter: str, values: tuple[float, float], steps: int,
                         start: int = 10, substeps: int = 10) -> np.ndarray:
    """|angle difference| (rad, wrapped) after ``steps`` frames between two hypotheses about one
    hidden parameter ('damping' or 'w0', set to ``values``), the other parameter at its true
    value, from each sequence's true state at frame ``start`` under its own actions: how much
    ``steps``-ahead prediction tells the two apart, next to :func:`angle_precision`."""
    if parameter not in ("damping", "w0"):
        raise ValueError(f"parameter must be 'damping' or 'w0', got {parameter!r}")
    if steps < 1 or start < 0 or start + steps > data.actions.shape[1]:
        raise ValueError(f"parameter_separation: start={start} + steps={steps} outside the "
                         f"{data.actions.shape[1]} frames")
    n = len(data)
    u = data.actions[:, start:start + steps + 1, 0].astype(np.float64)
    ends = []
    for v in values:
        w0 = np.full(n, float(v)) if parameter == "w0" else data.w0
        d = np.full(n, float(v)) if parameter == "damping" else data.damping
        theta, _ = integrate(data.theta[:, start], data.omega[:, start], w0, d, u, DT, substeps)
        ends.append(theta[:, -1])
    return np.abs(np.angle(np.exp(1j * (ends[0] - ends[1]))))


def least_squares_parameters(theta: np.ndarray, actions: np.ndarray, dt: float = DT) -> tuple[np.ndarray, np.ndarray]:
    """Per-sequence least-squares estimate of (w0, d) from an angle trajectory, told the
    equation of motion (not the labels): a reader with the true model structure, the
    reference an unsupervised filter's y is compared with (docs/reference/model.md, "Readers of the
    true angle").

    theta (N, T) angles at the start of each frame (rad, may wrap), actions (N, T) or
    (N, T, 1) the acceleration held over each frame. With central differences on the
    unwrapped angle, for 1 <= t <= T - 2,

        (theta_{t+1} - 2 theta_t + theta_{t-1}) / dt^2 - (u_{t-1} + u_t) / 2
            = -w0^2 sin(theta_t) - d (theta_{t+1} - theta_{t-1}) / (2 dt)

    is linear in (w0^2, d) and solved per sequence. Returns (w0, d), each (N,); w0 is
    sqrt(max(w0^2, 0))."""
    theta = np.unwrap(np.asarray(theta, dtype=np.float64), axis=-1)
    u = np.asarray(actions, dtype=np.float64)
    u = u[..., 0] if u.ndim == 3 else u
    if theta.ndim != 2 or u.shape != theta.shape or theta.shape[1] < 4:
        raise ValueError(f"least_squares_parameters: theta {theta.shape} and actions {u.shape} must both be "
                         f"(N, T) with T >= 4")
    acc = (theta[:, 2:] - 2 * theta[:, 1:-1] + theta[:, :-2]) / dt ** 2 - 0.5 * (u[:, :-2] + u[:, 1:-1])
    vel = (theta[:, 2:] - theta[:, :-2]) / (2 * dt)
    design = np.stack([-np.sin(theta[:, 1:-1]), -vel], -1)  # (N, T - 2, 2)
    coef = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in zip(design, acc)])
    return np.sqrt(np.maximum(coef[:, 0], 0.0)), coef[:, 1]
