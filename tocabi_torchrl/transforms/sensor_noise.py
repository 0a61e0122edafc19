"""Sensor biases and noise on what the policy observes: joint encoders, the IMU's Euler angles, the foot F/T sensors,
and the pelvis velocity (a state estimator's and a gyro's) where the observation reads it.

A real robot's sensors are offset (a calibration error, fixed over an episode) and noisy (fresh every control
period). :class:`SensorNoise` adds both to the per-step observation ``obs_step`` (num_envs, D), between
:class:`~tocabi_torchrl.transforms.ObservationAssembly` and the normalisation, on the columns that the observation
layout takes from each perturbed signal:

================ ========== ====== ================================================ =================================
signal           shape      unit   per-world bias, drawn at each reset              per-step noise
================ ========== ====== ================================================ =================================
``joint_pos``    (N, 33)    rad    U(±``joint_pos_bias``) per joint                 N(0, ``joint_pos_noise_std``)
                                                                                    clipped at ±clip, per joint
``joint_vel``    (N, 33)    rad/s  (none)                                           N(0, ``joint_vel_noise_std``)
                                                                                    clipped at ±clip, per joint
``base_rpy``     (N, 3)     rad    U(±``base_rpy_bias``) per roll, pitch, yaw axis  (none)
``foot_force``   (N, 2, 3)  N      U(±``foot_force_bias``) per axis and foot        (none)
``foot_torque``  (N, 2, 3)  N·m    U(±``foot_torque_bias``) per axis and foot       (none)
``base_lin_vel`` (N, 3)     m/s    U(±``base_lin_vel_bias``) per axis               N(0, ``base_lin_vel_noise_std``)
                                                                                    clipped at ±clip, per axis
``base_ang_vel`` (N, 3)     rad/s  U(±``base_ang_vel_bias``) per axis               N(0, ``base_ang_vel_noise_std``)
                                                                                    clipped at ±clip, per axis
================ ========== ====== ================================================ =================================

Where the noise goes. ``ObservationAssembly`` only gathers signal elements into columns (and casts to float32,
which the signals already are), so adding a value to a column of ``obs_step`` is exactly adding it to that signal
element before the assembly reads it. The raw keys (``joint_pos``, ``foot_force``, ...) stay the true signals, and
the reward terms, which read them, never see the perturbation; no noisy copy of a signal is stored with the rollout;
and the observation still names the raw signals, so an exported policy's contract (``export/``) lists the signals a
robot provides. The IMU bias is added to the Euler angles that the observation holds (``base_rpy``, from
:class:`~tocabi_torchrl.transforms.BaseEulerAngles`), not composed with ``base_quat`` as a small rotation: the
lab's numbers are per roll, pitch and yaw axis of those angles, and a rotation composed with the attitude would turn
into other Euler offsets (a roll offset becomes pitch as the robot turns). A biased angle beyond ±π is wrapped
back into (−π, π], the range of the unbiased one.

Random numbers. Every draw comes from the env's counter-based hash
(:func:`tocabi_torchrl.envs.episode_random.episode_uniform`), never from a generator, each signal with streams of
its own: a world's biases are keyed on (seed, env index, episode number, step 0) (:data:`BIAS_STREAMS`), the noise
of its episode's first observation on the same key (:data:`NOISE_STREAMS`), and the noise of observation k >= 1 on
the key of step k − 1 (:data:`LATER_NOISE_STREAMS`). In training the masked reset runs after every step, keyed on
each world's (episode, step): one hash pass there draws a reset world's biases and first noise and every world's
next noise, and the step reads that noise instead of hashing again (a step that no reset preceded hashes it, and
so does a step being captured into a CUDA graph, whose replays need not follow a reset). World i's draws therefore
depend neither on the other worlds nor on how often or in which order reset and step run, and the noise of a step
is a function of the env's device counters, so a captured CUDA graph of the step draws fresh numbers on every
replay without any Python state. The biases live in (N, ...) device tensors, redrawn in place with ``torch.where`` for
the worlds a reset flags: no host reads. Normals are Box-Muller pairs of those uniforms.

>>> from tocabi_torchrl.transforms import SensorNoiseConfig
>>> cfg = SensorNoiseConfig.tocabi_lab()
>>> cfg.enabled, round(cfg.joint_pos_bias, 5), cfg.joint_pos_noise_clip
(True, 0.03142, 0.00016)
>>> SensorNoiseConfig().enabled  # the default adds no transform
False
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from tocabi_torchrl import robot
from tocabi_torchrl.envs.episode_random import EpisodeDraws, LaneDraws, stream_lanes
from tocabi_torchrl.transforms._base import transforms_after, transforms_before
from tocabi_torchrl.transforms._checks import require_spec
from tocabi_torchrl.transforms.history import ObsActionHistory
from tocabi_torchrl.transforms.normalize import _Normalization
from tocabi_torchrl.transforms.observation import REFERENCE_OBS_LAYOUT, ObservationAssembly, ObsComponent
# The config lives in a module without torch, for the config tree; this path names it too.
from tocabi_torchrl.transforms.sensor_noise_config import SENSORS, SensorNoiseConfig

__all__ = ["SensorNoiseConfig", "SensorNoise", "SENSORS", "BIAS_STREAMS", "NOISE_STREAMS", "LATER_NOISE_STREAMS",
           "sensor_biases", "sensor_noise"]

#: Hash stream of each signal's per-episode bias, of the noise of an episode's first observation, and of the noise of
#: its later observations (``episode_uniform``'s ``stream``). The env's per-episode draws use streams below 32 and its
#: start pool 48-50 (``envs/tocabi_walk.py``); one stream per signal keeps a signal's numbers the same whichever other
#: signals are perturbed.
BIAS_STREAMS: Mapping[str, int] = {name: 32 + i for i, name in enumerate(SENSORS)}
NOISE_STREAMS: Mapping[str, int] = {name: 40 + i for i, name in enumerate(SENSORS)}
LATER_NOISE_STREAMS: Mapping[str, int] = {name: 52 + i for i, name in enumerate(SENSORS)}
assert max(BIAS_STREAMS.values()) < min(NOISE_STREAMS.values()) and max(NOISE_STREAMS.values()) < 48, (
    "the sensor streams would run into each other or into the start pool's (48-50)")
assert min(LATER_NOISE_STREAMS.values()) > 50, "the later noise's streams would run into the start pool's (48-50)"
# The step occupies the low 32 bits of the noise key, the episode number the bits above (2**32 steps = 198 days).
_STEP_BITS = 32


def _key(episode: torch.Tensor, step: torch.Tensor | int = 0) -> torch.Tensor:
    """(N,) int64 hash key of each world's (``episode``, ``step``); the biases use step 0's."""
    step = step.to(torch.int64) if isinstance(step, torch.Tensor) else step
    return (episode.to(torch.int64) << _STEP_BITS) + step


def _normals(u: torch.Tensor, k: int) -> torch.Tensor:
    """(N, k) standard normals from (N, 2·ceil(k/2)) uniforms: Box-Muller, both the cosine and the sine of each pair
    used."""
    m = (k + 1) // 2
    radius = torch.sqrt(-2.0 * torch.log1p(-u[:, :m]))  # 1 - u in (0, 1]: the log is finite
    angle = (2.0 * math.pi) * u[:, m:]
    return torch.cat((radius * torch.cos(angle), radius * torch.sin(angle)), dim=-1)[:, :k]


def _bias_draws(config: SensorNoiseConfig, device) -> EpisodeDraws:
    """One hash pass for every biased signal's uniforms (its own stream each)."""
    return EpisodeDraws({BIAS_STREAMS[name]: math.prod(shape) for name, shape in SENSORS.items()
                         if config.bias(name) > 0}, device)


def _noise_draws(config: SensorNoiseConfig, streams: Mapping[str, int], device) -> EpisodeDraws:
    """One hash pass for every noisy signal's Box-Muller uniforms (its own stream of ``streams`` each)."""
    return EpisodeDraws({streams[name]: 2 * ((math.prod(shape) + 1) // 2) for name, shape in SENSORS.items()
                         if config.noise(name)[0] > 0}, device)


def _biases(config: SensorNoiseConfig, draws: EpisodeDraws, seed, env_ids: torch.Tensor,
            episode: torch.Tensor) -> dict[str, torch.Tensor]:
    u = draws(seed, env_ids, _key(episode))
    return {name: (config.bias(name) * (2.0 * u[BIAS_STREAMS[name]] - 1.0)).reshape(-1, *shape)
            for name, shape in SENSORS.items() if config.bias(name) > 0}


def _noise(config: SensorNoiseConfig, seed, env_ids: torch.Tensor, episode: torch.Tensor,
           step: torch.Tensor) -> dict[str, torch.Tensor]:
    step = step.to(torch.int64)
    first = _noise_draws(config, NOISE_STREAMS, env_ids.device)(seed, env_ids, _key(episode))
    later = _noise_draws(config, LATER_NOISE_STREAMS, env_ids.device)(seed, env_ids,
                                                                      _key(episode, (step - 1).clamp(min=0)))
    out = {}
    for name, shape in SENSORS.items():
        std, clip = config.noise(name)
        if std > 0:
            k = math.prod(shape)
            z = std * torch.where((step == 0).unsqueeze(-1), _normals(first[NOISE_STREAMS[name]], k),
                                  _normals(later[LATER_NOISE_STREAMS[name]], k))
            if clip is not None:
                z = z.clamp(-clip, clip)
            out[name] = z.reshape(-1, *shape)
    return out


def sensor_biases(config: SensorNoiseConfig, seed: int | torch.Tensor, env_ids: torch.Tensor,
                  episode: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each biased signal's bias for each world's ``episode``: ``{signal: (N, *SENSORS[signal])}`` float32 in the
    signal's unit, U(±half-width) per element, keyed on the episode's step 0. ``env_ids``, ``episode``: (N,)
    int64; ``seed``: an int or a 0-d int64 tensor on their device."""
    return _biases(config, _bias_draws(config, env_ids.device), seed, env_ids, episode)


def sensor_noise(config: SensorNoiseConfig, seed: int | torch.Tensor, env_ids: torch.Tensor, episode: torch.Tensor,
                 step: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each noisy signal's noise at each world's (``episode``, ``step``): ``{signal: (N, *SENSORS[signal])}``
    float32, N(0, σ²) per element, clipped to ±clip. ``step``: (N,) int64 policy steps since the episode began (the
    env's ``episode_step``), below 2**32. Step 0's noise is keyed on (``episode``, 0) with :data:`NOISE_STREAMS`,
    step k's from k = 1 on on (``episode``, k − 1) with :data:`LATER_NOISE_STREAMS`: the key the masked reset after
    step k − 1 holds, so that it draws the next observation's noise in its own hash pass."""
    return _noise(config, seed, env_ids, episode, step)


_KEY_SOURCE = ("_seed_t", "_env_ids", "episode_count", "episode_step")


class SensorNoise(Transform):
    """Adds per-world sensor biases and per-step sensor noise to the observation ``obs_key`` (see the module doc).

    Reads and rewrites ``obs_key`` (num_envs, D) float32, whose columns ``layout`` describes (the layout given to
    :class:`~tocabi_torchrl.transforms.ObservationAssembly`); put it right after that transform. The raw signal keys
    are left as they are. Runs on every step and on reset; at a reset the flagged worlds get new biases first.
    The random numbers are keyed on the base env's device counters (``TocabiWalk``'s ``_seed_t``, ``_env_ids``,
    ``episode_count``, ``episode_step``), so the transform belongs to one env.

    Attributes:
        biases: ``{signal: (num_envs, *shape)}`` the current bias of each world [the signal's unit] (after the
            first reset).

    Args:
        config: the ranges (:class:`SensorNoiseConfig`); an all-zero one is refused (leave the transform out).
        layout: the observation's blocks; every perturbed signal must be read by one.
        obs_key: the per-step observation the noise is added to.

    >>> import torch
    >>> from tocabi_torchrl import make_env
    >>> from tocabi_torchrl.transforms import SensorNoiseConfig
    >>> env = make_env(num_envs=2, device="cpu", seed=0, sensor_noise=SensorNoiseConfig.tocabi_lab())
    >>> td = env.reset()
    >>> noise = next(t for t in env.transform if isinstance(t, SensorNoise))
    >>> tuple(noise.biases["joint_pos"].shape), bool(noise.biases["joint_pos"].abs().max() <= torch.pi / 100)
    ((2, 33), True)
    """

    def __init__(self, config: SensorNoiseConfig, layout: tuple[ObsComponent, ...] = REFERENCE_OBS_LAYOUT,
                 obs_key: NestedKey = "obs_step"):
        if not isinstance(config, SensorNoiseConfig):
            raise TypeError(f"SensorNoise takes a SensorNoiseConfig, e.g. SensorNoiseConfig.tocabi_lab(), got "
                            f"{type(config).__name__}")
        if not config.enabled:
            raise ValueError("SensorNoise got a config that perturbs nothing (every bias and noise is 0); leave the "
                             "transform out, or set a range, e.g. SensorNoiseConfig.tocabi_lab()")
        layout = tuple(layout)
        read = {c.key for c in layout}
        missing = [name for name in config.perturbed() if name not in read]
        if missing:
            raise ValueError(f"SensorNoise perturbs {missing}, which the observation layout does not read (its keys: "
                             f"{sorted(map(str, read))}); set those ranges to 0 or add the signal to the layout")
        super().__init__(in_keys=[obs_key], out_keys=[obs_key])
        self.config = config
        self.layout = layout
        self.biases: dict[str, torch.Tensor] = {}
        # Column maps, from the specs: per perturbed signal, which obs columns take which of its flat elements.
        self._columns: dict[str, tuple[list[int], list[int]]] | None = None
        self._width = 0
        self._source: tuple[torch.Tensor, ...] | None = None
        self._worlds: torch.Tensor | None = None
        self._index: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        # Host flag: a reset ran since the last step, so _noise_next holds every world's next noise.
        self._next_drawn = False

    # ---------------------------------------------------------------------------------------------- set-up
    def _check_place(self) -> None:
        """Refuse a place where the noise would reach nothing the policy sees, silently: after the transform that
        builds the policy input from ``obs_key`` (a normalisation, the history), whatever reads it behind (a log
        copy), or after any other reader of it with nothing behind reading it. A transform in front that only reads
        it (a clean copy for a critic or a log) is fine while the policy input is built behind."""
        key = self.in_keys[0]
        self._check_layout(key)
        # One that rewrites obs_step in place passes the noise on.
        readers = [t for t in transforms_before(self) if key in t.in_keys and key not in t.out_keys]
        builds_input = [t for t in readers if isinstance(t, (_Normalization, ObsActionHistory))]
        if builds_input:
            why = f"which builds the policy input from {key!r} already"
        elif readers and not any(key in t.in_keys for t in transforms_after(self)):
            why = f"which reads {key!r} already, and nothing behind it reads {key!r}"
        else:
            return
        raise ValueError(f"SensorNoise comes after {type((builds_input or readers)[-1]).__name__}, {why}, so the noise "
                         "would reach nothing the policy sees; put SensorNoise right after ObservationAssembly (as "
                         "default_transforms does)")

    def _check_layout(self, key: NestedKey) -> None:
        """Refuse a layout other than that of the ObservationAssembly in front writing ``key``: the columns are mapped
        from this transform's layout, so with the same width (blocks reordered or swapped) a signal's bias and noise
        landed on another's columns without a word (joint-position noise on joint velocities)."""
        assemblies = [t for t in transforms_before(self) if isinstance(t, ObservationAssembly) and key in t.out_keys]
        columns = lambda layout: [(c.key, c.index) for c in layout]  # noqa: E731 - what each block reads, not its label
        if assemblies and columns(assemblies[-1].layout) != columns(self.layout):
            names = lambda layout: [c.name for c in layout]  # noqa: E731
            raise ValueError(f"SensorNoise was given a layout (blocks {names(self.layout)}) other than that of the "
                             f"ObservationAssembly in front of it that writes {key!r} (blocks "
                             f"{names(assemblies[-1].layout)}), so its noise would land on other columns; pass it "
                             "that layout: SensorNoise(config, assembly.layout)")

    def _map_columns(self, spec: Composite) -> None:
        batch = tuple(spec.shape)
        perturbed = self.config.perturbed()
        columns: dict[str, tuple[list[int], list[int]]] = {name: ([], []) for name in perturbed}
        start = 0
        for c in self.layout:
            shape = tuple(require_spec(spec, c.key, self).shape)[len(batch):]
            if c.key in columns and shape != SENSORS[c.key]:
                raise ValueError(f"SensorNoise expects {c.key!r} of shape (num_envs, *{SENSORS[c.key]}), the env "
                                 f"gives (num_envs, *{shape}); perturb the signals of TocabiWalk "
                                 "(docs/concepts/env-and-signals.md) "
                                 "or set that range to 0")
            # The block's flat elements, in the order ObservationAssembly concatenates them.
            elements = torch.arange(math.prod(shape)).reshape(shape)[c.index].flatten()
            if c.key in columns:
                cols, elems = columns[c.key]
                cols.extend(range(start, start + elements.numel()))
                elems.extend(elements.tolist())
            start += elements.numel()
        obs = require_spec(spec, self.in_keys[0], self)
        if obs.shape[-1] != start:
            raise ValueError(f"SensorNoise: {self.in_keys[0]!r} has {obs.shape[-1]} columns but the layout gives "
                             f"{start}; pass SensorNoise the layout of the ObservationAssembly in front of it")
        if columns != self._columns:
            self._columns, self._width, self._index, self.biases = columns, start, {}, {}

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        self._map_columns(observation_spec)  # nothing new to declare: obs_key keeps its spec
        self._source = None  # the env may have changed
        return observation_spec

    def _key_source(self) -> tuple[torch.Tensor, ...]:
        if self._source is None:
            parent = self.parent
            base = getattr(parent, "base_env", parent)
            missing = [name for name in _KEY_SOURCE if not isinstance(getattr(base, name, None), torch.Tensor)]
            if missing:
                raise TypeError(f"SensorNoise keys its random numbers on the env's counters {list(_KEY_SOURCE)}, "
                                f"which {type(base).__name__} lacks ({missing}); use it on a TocabiWalk (make_env, "
                                "default_transforms)")
            self._source = tuple(getattr(base, name) for name in _KEY_SOURCE)
            # (N,) bool: the worlds with noisy sensors; the env's others are exact (TocabiWalk.set_randomized_worlds).
            worlds = getattr(base, "randomized_worlds", None)
            self._worlds = worlds.unsqueeze(-1) if isinstance(worlds, torch.Tensor) else None
        if self._columns is None:
            self._map_columns(self.parent.observation_spec)
        return self._source

    def _materialise(self) -> None:
        """Index tensors, hash lanes and bias buffers on the env's device (once, eagerly: the first reset runs before
        any capture); the first reset then draws every world's biases."""
        env_ids = self._source[1]
        if self._index:
            return
        dev = env_ids.device
        self._index = {name: (torch.tensor(cols, dtype=torch.int64, device=dev),
                              torch.tensor(elems, dtype=torch.int64, device=dev))
                       for name, (cols, elems) in self._columns.items()}
        n, biased = env_ids.shape[0], [name for name in SENSORS if self.config.bias(name) > 0]
        sizes = [math.prod(SENSORS[name]) for name in biased]
        offsets = [sum(sizes[:i]) for i in range(len(sizes))]
        # Every bias in one (N, B) buffer, the signals side by side, so that a reset redraws them all with a handful
        # of ops; ``biases`` holds (N, *shape) views of it.
        self._bias_flat = torch.zeros(n, sum(sizes), dtype=torch.float32, device=dev)
        self._bias_half = torch.tensor([self.config.bias(name) for name, k in zip(biased, sizes) for _ in range(k)],
                                       dtype=torch.float32, device=dev)
        self.biases = {name: self._bias_flat[:, o:o + k].view(n, *SENSORS[name])
                       for name, o, k in zip(biased, offsets, sizes)}
        # Column c of the observation takes element _bias_src[c] of the buffer, times _bias_on[c] (0: unbiased).
        src = torch.zeros(self._width, dtype=torch.int64)
        on = torch.zeros(self._width, dtype=torch.float32)
        for name, o in zip(biased, offsets):
            cols, elems = self._columns[name]
            src[cols] = torch.tensor(elems, dtype=torch.int64) + o
            on[cols] = 1.0
        self._bias_src, self._bias_on = src.to(dev), on.to(dev)
        self._bias_cols = torch.zeros(n, self._width, dtype=torch.float32, device=dev)
        first, later = self._map_noise(n, dev)
        bias_lanes = [stream_lanes(BIAS_STREAMS[name], k, dev) for name, k in zip(biased, sizes)]
        # The masked reset (every step in training) draws, in one hash pass keyed on each world's (episode, step):
        # a reset world's biases and first noise (its step is 0, the biases' key) and every world's next noise. A
        # step then reads that next noise; it hashes only when no reset ran since the last step, or under capture.
        p = self._pairs
        self._reset_hash = LaneDraws(torch.cat((*bias_lanes, first[:p], later[:p], first[p:], later[p:])))
        self._step_hash = LaneDraws(later)
        # The Euler angles' columns are wrapped back into (-pi, pi] after the bias: (D,) bounds, ±pi there and ±inf
        # in the other columns, so that the wrap is two compares over the whole observation.
        self._wrap = None
        if "base_rpy" in self.biases:
            upper = torch.full((self._width,), math.inf, dtype=torch.float32)
            upper[self._columns["base_rpy"][0]] = math.pi
            self._wrap = (upper.to(dev), (-upper).to(dev))

    def _map_noise(self, n: int, dev) -> tuple[torch.Tensor, torch.Tensor]:
        """Lay out every noisy signal's Box-Muller pairs for one pass and set the maps from their normals to the
        observation's noisy columns. Returns the (2P,) hash lanes of the first and of the later noise
        (:data:`NOISE_STREAMS`, :data:`LATER_NOISE_STREAMS`), each the P pairs' radius uniforms, then their angle
        uniforms (each signal's own lanes, as :func:`sensor_noise` reads them)."""
        first, later, cols, elements, std, clip = ([], []), ([], []), [], [], [], []
        pairs = sum((math.prod(SENSORS[name]) + 1) // 2 for name in SENSORS if self.config.noise(name)[0] > 0)
        start = 0  # this signal's first pair
        for name, shape in SENSORS.items():
            sigma, limit = self.config.noise(name)
            if sigma <= 0:
                continue
            m = (math.prod(shape) + 1) // 2
            for lanes, streams in ((first, NOISE_STREAMS), (later, LATER_NOISE_STREAMS)):
                block = stream_lanes(streams[name], 2 * m, dev)
                lanes[0].append(block[:m])
                lanes[1].append(block[m:])
            # Element e < m is pair e's cosine normal, element e >= m pair (e - m)'s sine one.
            for col, e in zip(*self._columns[name]):
                cols.append(col)
                elements.append((start + e, False) if e < m else (start + e - m, True))
                std.append(sigma)
                clip.append(math.inf if limit is None else limit)
            start += m
        self._pairs = pairs
        empty = torch.zeros(0, dtype=torch.int64, device=dev)
        if not cols:
            self._noise_cols = None
            return empty, empty
        # Normals side by side as Box-Muller gives them: a step's (N, 2P) [cos | sin] of the later noise, a reset's
        # (N, 4P) [cos first | cos later | sin first | sin later].
        step_src = [pair + pairs * sine for pair, sine in elements]
        first_src = [pair + 2 * pairs * sine for pair, sine in elements]
        tensor = lambda values, dtype=torch.int64: torch.tensor(values, dtype=dtype, device=dev)
        self._noise_cols = tensor(cols)
        self._step_src = tensor(step_src)
        self._reset_src = tensor(first_src + [i + pairs for i in first_src])  # (2C,): first, then later
        self._noise_std = tensor(std * 2, torch.float32)
        self._noise_clip = tensor(clip * 2, torch.float32)
        self._noise_floor = -self._noise_clip  # the lower bound, made once rather than negated every step
        c = len(cols)
        #: (N, C) the noise of each world's latest observation, and of its next one as the last reset drew it.
        self._noise_now = torch.zeros(n, c, dtype=torch.float32, device=dev)
        self._noise_next = torch.zeros(n, c, dtype=torch.float32, device=dev)
        cat = lambda parts: torch.cat(parts) if parts else empty
        return torch.cat((cat(first[0]), cat(first[1]))), torch.cat((cat(later[0]), cat(later[1])))

    def _drawn_biases(self, u: torch.Tensor) -> torch.Tensor:
        """(N, B) every bias from the reset hash's uniforms ``u`` (N, B + 4P), U(±half-width), as
        :func:`sensor_biases` draws them."""
        return self._bias_half * (2.0 * u[:, :self._bias_half.shape[0]] - 1.0)

    def _gather_biases(self) -> None:
        """``_bias_cols`` (N, D): each world's bias in the obs columns of its signals, 0 elsewhere (in place)."""
        self._bias_cols.copy_(self._bias_flat.index_select(1, self._bias_src) * self._bias_on)

    def _scaled_noise(self, u: torch.Tensor, src: torch.Tensor) -> torch.Tensor:
        """The noisy columns' noise from Box-Muller uniforms ``u`` (N, 2Q): the Q pairs' normals, picked per column by
        ``src``, scaled by the column's σ and clipped (the first ``len(src)`` columns of σ and clip)."""
        k = src.shape[0]
        noise = _normals(u, u.shape[1]).index_select(1, src) * self._noise_std[:k]
        return noise.clamp(self._noise_floor[:k], self._noise_clip[:k])

    def _perturbed(self, exact: torch.Tensor) -> torch.Tensor:
        """(N, D) the observation ``exact`` plus each world's biases and the noise of its latest observation."""
        obs = exact + self._bias_cols
        if self._noise_cols is not None:
            obs = obs.index_add(1, self._noise_cols, self._noise_now)
        if self._wrap is not None:
            (upper, lower), two_pi = self._wrap, 2.0 * math.pi
            obs = torch.where(obs > upper, obs - two_pi, torch.where(obs <= lower, obs + two_pi, obs))
        if self._worlds is not None:
            obs = torch.where(self._worlds, obs, exact)
        return obs

    # ------------------------------------------------------------------------------------------------ calls
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        seed, env_ids, episode, step = self._key_source()
        n = env_ids.shape[0]
        if not self._index:
            # Here, not with the specs: torchrl computes a later transform's specs on copies of the chain in front
            # of it, where nothing is behind this transform.
            self._check_place()
            self._materialise()
            mask = torch.ones(n, dtype=torch.bool, device=env_ids.device)
        else:
            reset = None if tensordict is None else tensordict.get("_reset", None)
            mask = torch.ones(n, dtype=torch.bool, device=env_ids.device) if reset is None else reset.reshape(n)
        # The base env has counted the new episode and zeroed its step already: a flagged world's key is its new
        # episode's step 0, the biases' key. The other worlds' bias and first-noise uniforms go unused.
        u = self._reset_hash(seed, env_ids, _key(episode, step))
        m = mask.unsqueeze(-1)
        torch.where(m, self._drawn_biases(u), self._bias_flat, out=self._bias_flat)
        self._gather_biases()
        if self._noise_cols is not None:
            noise = self._scaled_noise(u[:, self._bias_half.shape[0]:], self._reset_src)  # (N, 2C): first, next
            c = self._noise_now.shape[1]
            torch.where(m, noise[:, :c], self._noise_now, out=self._noise_now)
            self._noise_next.copy_(noise[:, c:])
            self._next_drawn = True
        self._share_with_assist(mask)
        tensordict_reset.set(self.out_keys[0], self._perturbed(tensordict_reset.get(self.in_keys[0])))
        return tensordict_reset

    def _share_with_assist(self, mask: torch.Tensor) -> None:
        """The reset worlds' leg encoder biases into the torque assist's PD, when the env's PD reads the sensed
        positions (``TocabiWalk.sense_assist_joints``): one source for the observation's bias and the PD's."""
        base = getattr(self.parent, "base_env", self.parent)
        if not getattr(base, "assist_reads_sensed", False) or "joint_pos" not in self.biases:
            return
        bias = self.biases["joint_pos"][:, robot.LEGS]
        base.leg_controller.set_q_offset(mask, bias if self._worlds is None else bias * self._worlds)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        seed, env_ids, episode, step = self._key_source()
        if not self._index:
            raise RuntimeError("SensorNoise: reset the env before stepping it (the biases are drawn at reset)")
        if self._noise_cols is not None:
            # The masked reset after the last step drew this observation's noise. A step being captured into a CUDA
            # graph hashes anyway: its replays need not follow a reset.
            if self._next_drawn and not (env_ids.is_cuda and torch.cuda.is_current_stream_capturing()):
                self._noise_now.copy_(self._noise_next)
            else:
                u = self._step_hash(seed, env_ids, _key(episode, step - 1))
                self._noise_now.copy_(self._scaled_noise(u, self._step_src))
            self._next_drawn = False
        next_tensordict.set(self.out_keys[0], self._perturbed(next_tensordict.get(self.in_keys[0])))
        return next_tensordict

    def clone(self) -> SensorNoise:
        """A copy bound to no env yet: its first reset maps its env's counters and draws its own biases."""
        copy = super().clone()
        # torchrl's clone is shallow: the copy kept the env's counters and shared the bias and noise buffers, so a
        # second env's resets redrew the first env's biases in place.
        copy._source, copy._worlds, copy._index, copy.biases, copy._next_drawn = None, None, {}, {}, False
        return copy

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Stored data (a replay buffer sample) passes unchanged: the noise belongs to the env's steps, keyed on
        its counters, and a stored ``obs_step`` already holds it."""
        return tensordict

    def __repr__(self) -> str:
        return f"{type(self).__name__}(signals={list(self.config.perturbed())}, obs_key={self.in_keys[0]!r})"
