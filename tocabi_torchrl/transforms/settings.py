"""The transforms' configuration as plain values: :class:`TransformConfig` (everything
:func:`~tocabi_torchrl.transforms.presets.default_transforms` builds), the named :data:`HISTORIES`, and
:class:`TransformSettings`, the transforms section of the run config tree.

A module without torch, so that the config tree (and ``recipes/ppo_walk.py --help``) reads without loading it;
``presets`` builds the transforms from these values, and names them too.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

from tocabi_torchrl.transforms._checks import check_positive_int
from tocabi_torchrl.transforms.kick_relax_config import KickRelax
from tocabi_torchrl.transforms.layouts import (NON_PHASE_VALUES, OBS_LAYOUTS, REFERENCE_HISTORY, REFERENCE_OBS_LAYOUT,
                                               TOCABILAB_HISTORY, HistoryLayout, ObsComponent, layout_name)
from tocabi_torchrl.transforms.sensor_noise_config import SensorNoiseConfig
from tocabi_torchrl.tree import check_field_types

__all__ = ["TransformConfig", "TransformSettings", "RewardWeights", "HISTORIES", "NORMALIZATIONS", "transform_config",
           "REFERENCE_TERM_NAMES"]

#: The observation normalisations (``transforms.normalization``).
NORMALIZATIONS = ("fixed", "running", "none")
#: The names of ``reward_terms.REFERENCE_TERMS`` (the reference's terms, in its order), here so that the config checks
#: a term name without the terms' torch code; tests/test_transforms_presets.py checks that the two agree.
REFERENCE_TERM_NAMES = ("orientation", "qpos", "qvel", "body_vel", "contact_force", "torque", "torque_diff", "qacc",
                        "foot_contact", "contact_force_diff", "force_ref", "force_threshold", "force_diff_threshold")


#: The normaliser clips its output, so without one a clip was silently not applied (the raw observation went on,
#: foot forces of hundreds of N included).
_CLIP_WITHOUT_NORMALIZATION = ("{prefix}obs_clip {clip!r} clips the normalised observation, and {prefix}normalization "
                               "is 'none' (no normaliser, so nothing would be clipped): use {prefix}normalization "
                               "'fixed' or 'running', or {prefix}obs_clip None")
#: A clip <= 0 passed the config and was refused only when the normaliser was built, without the option's path.
_CLIP_NOT_POSITIVE = ("{prefix}obs_clip must be a finite number > 0 (the normalised observation is clipped to "
                      "[-obs_clip, obs_clip]) or None for no clip, got {clip!r}")


@dataclass(frozen=True)
class TransformConfig:
    """Everything :func:`default_transforms` builds, as plain values.

    Attributes:
        phase_harmonics: sin/cos harmonics of the phase (1 in the reference).
        obs_layout: blocks of the per-step observation (:data:`REFERENCE_OBS_LAYOUT`: 37 values).
        normalization: ``"fixed"`` (reference statistics or ``obs_mean``/``obs_var``), ``"running"`` (running
            statistics, initialised from ``obs_mean``/``obs_var`` when given) or ``"none"``.
        obs_mean, obs_var: statistics for the normalisation, one per per-step observation value (default: the
            reference's, spec §7.1); refused with ``normalization="none"``, which reads none, and with a length
            other than :meth:`step_obs_size` (when the config sets it, else once the env's observation is known).
        obs_clip: optional clip of the normalised observation, > 0 (the reference has none); refused with
            ``normalization="none"``, which has nothing to clip.
        history: observation + action history layout (:data:`REFERENCE_HISTORY`: 5 obs every 2 steps + 4 actions).
        reward_terms: term names from :data:`REFERENCE_TERM_NAMES` and/or :class:`RewardTerm` instances / callables.
        reward_weights: ``{term name: weight}`` overrides.
        reward_scales: ``{term name: scale}`` overrides of a term's kernel sharpness (its ``scale`` field, e.g.
            ``{"body_vel": 8.0}`` for ``exp(-8·‖v - cmd‖²)``); each must be a finite number > 0.
        zero_reward_on_terminated: reward and terms are 0 on a terminating step (reference: on).
        compile_reward: ``torch.compile`` the reward terms into fused kernels (first step compiles).
        max_episode_steps: ``StepCounter`` truncation at this many steps, on top of the env's own; ``None`` (the
            default) counts steps without truncating, so the env's ``task.max_episode_steps`` is the one clock.
        track_episode_return: add ``RewardSum`` (``episode_reward``).
        sensor_noise: sensor biases and noise on the observation (:class:`SensorNoiseConfig`; all 0 = none).
        kick_relax: reward terms relaxed while a kicked robot recovers (:class:`KickRelax`; seconds 0 = none).
    """

    phase_harmonics: int = 1
    obs_layout: tuple[ObsComponent, ...] = REFERENCE_OBS_LAYOUT
    normalization: str = "fixed"
    obs_mean: Sequence[float] | None = None
    obs_var: Sequence[float] | None = None
    obs_clip: float | None = None
    history: HistoryLayout = REFERENCE_HISTORY
    reward_terms: tuple = REFERENCE_TERM_NAMES
    reward_weights: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    reward_scales: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    zero_reward_on_terminated: bool = True
    compile_reward: bool = False
    # None, not the env's default 8000: a fixed limit here would cut an env configured for longer episodes.
    max_episode_steps: int | None = None
    track_episode_return: bool = True
    sensor_noise: SensorNoiseConfig = field(default_factory=SensorNoiseConfig)
    kick_relax: KickRelax = field(default_factory=KickRelax)

    def __post_init__(self):
        # Frozen copies, so that a preset cannot be changed through a config built from it.
        object.__setattr__(self, "reward_weights", MappingProxyType(dict(self.reward_weights)))
        object.__setattr__(self, "reward_scales", MappingProxyType(dict(self.reward_scales)))
        object.__setattr__(self, "reward_terms", tuple(self.reward_terms))
        object.__setattr__(self, "obs_layout", tuple(self.obs_layout))
        for name in ("obs_mean", "obs_var"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        if self.normalization not in NORMALIZATIONS:
            raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {self.normalization!r}")
        for name, kind in (("sensor_noise", SensorNoiseConfig), ("kick_relax", KickRelax)):
            object.__setattr__(self, name, _section(getattr(self, name), kind, name))
        if not isinstance(self.history, HistoryLayout):  # before the general check: this one names the layouts
            raise TypeError(
                f"history must be a HistoryLayout (REFERENCE_HISTORY, TOCABILAB_HISTORY or e.g. "
                f"HistoryLayout(num_obs=5, stride=2), from tocabi_torchrl.transforms), got {self.history!r}"
                + (f"; to pick one by name, pass transforms=TransformSettings(history={self.history!r})"
                   if isinstance(self.history, str) else "")
            )
        check_field_types(self)
        if (self.obs_mean is None) != (self.obs_var is None):
            raise ValueError("pass both obs_mean and obs_var, or neither (for the reference statistics)")
        if self.obs_clip is not None and not self.obs_clip > 0:  # check_field_types refused NaN and inf
            raise ValueError(_CLIP_NOT_POSITIVE.format(prefix="", clip=self.obs_clip))
        if self.obs_clip is not None and self.normalization == "none":
            raise ValueError(_CLIP_WITHOUT_NORMALIZATION.format(prefix="", clip=self.obs_clip))
        if self.obs_mean is not None and self.normalization == "none":
            # Without a normaliser nothing reads them, so statistics given for it were silently not applied.
            raise ValueError("obs_mean/obs_var are the normaliser's statistics, and normalization is 'none' (no "
                             "normaliser, so they would not be used): use normalization 'fixed' (these statistics) or "
                             "'running' (starting from them), or leave obs_mean and obs_var None")
        if self.max_episode_steps is not None:
            check_positive_int(self.max_episode_steps, "max_episode_steps", "or None to only count steps")
        check_positive_int(self.phase_harmonics, "phase_harmonics")
        if self.obs_mean is not None:
            self._check_stats_length()
        for t in self.reward_terms:
            if isinstance(t, str) and t not in REFERENCE_TERM_NAMES:
                raise KeyError(
                    f"unknown reward term {t!r}; known terms: {list(REFERENCE_TERM_NAMES)} "
                    "(pass a RewardTerm instance or a callable for your own term)"
                )
        for name, scale in self.reward_scales.items():
            if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 < scale < math.inf:
                raise ValueError(f"reward_scales[{name!r}] must be a finite number > 0 (the term's kernel scale), "
                                 f"got {scale!r}")

    def step_obs_size(self) -> int | None:
        """The number of per-step observation values (``obs_step``'s last dim, which ``obs_mean``/``obs_var`` hold
        one statistic each for) where the config alone sets it: a named ``obs_layout`` (``layouts.OBS_LAYOUTS``)
        reads TOCABI's fixed-size signals plus ``phase_harmonics`` sines and cosines (37 values for the reference's
        with 1 harmonic, 43 for ``base_vel``'s); ``None`` for a layout of one's own, whose size the env's signal
        shapes set."""
        name = layout_name(self.obs_layout)
        if name is None:
            return None
        return NON_PHASE_VALUES[name] + 2 * self.phase_harmonics

    def _check_stats_length(self) -> None:
        # A wrong length passed here and failed only once the transforms met an env's observation spec, naming the
        # normaliser's class rather than these fields.
        n_mean, n_var = len(self.obs_mean), len(self.obs_var)
        if n_mean != n_var:
            raise ValueError(f"obs_mean has {n_mean} values but obs_var has {n_var}; pass one mean and one variance "
                             "per per-step observation value")
        size = self.step_obs_size()
        if size is not None and n_mean != size:
            # What None gives follows presets._normalization: our statistics exist for the named layouts with 1
            # harmonic only; 'running' starts from them there, and from mean 0, variance 1 otherwise.
            name = layout_name(self.obs_layout)
            if self.phase_harmonics == 1:
                running = self.normalization == "running"
                fallback = (f", or leave both None for the {name} layout's statistics"
                            + (" (normalization 'running' starts from them)" if running else ""))
            elif self.normalization == "running":
                fallback = ", or leave both None (normalization 'running' then starts from mean 0 and variance 1)"
            else:
                fallback = (f" (the {name} layout's statistics are for phase_harmonics=1, so normalization "
                            f"'{self.normalization}' needs them)")
            raise ValueError(
                f"obs_mean/obs_var have {n_mean} values each but the per-step observation has {size} (the {name} "
                f"obs_layout: {NON_PHASE_VALUES[name]} values + sin and cos of phase_harmonics="
                f"{self.phase_harmonics}); pass {size} of each{fallback}")


def _section(value, kind: type, where: str, dicts: bool = True):
    """``value`` as a ``kind`` section: itself, or (``dicts``) built from a dict of its options; ``ValueError``
    naming ``where`` for anything else (None once failed later as an ``AttributeError``)."""
    if isinstance(value, kind):
        return value
    if dicts and isinstance(value, Mapping):
        from tocabi_torchrl.tree import from_dict

        return from_dict(kind, dict(value), f"{where}.")
    raise ValueError(f"{where} must be a {kind.__name__}{' or a dict of its options' if dicts else ''}, got "
                     f"{value!r}; for none, give {kind.__name__}() (all off)")


#: ``reference``: the reference task (spec §7-8). ``tocabilab``: the same, with TocabiLab's consecutive history
#: (last 5 observations, last 4 applied actions).
HISTORIES: Mapping[str, TransformConfig] = MappingProxyType(
    {
        "reference": TransformConfig(),
        "tocabilab": TransformConfig(history=TOCABILAB_HISTORY),
    }
)


def transform_config(base: str | TransformConfig = "reference", /, **overrides) -> TransformConfig:
    """The :class:`TransformConfig` of ``base`` (the name of a history layout in :data:`HISTORIES`, or a
    :class:`TransformConfig` to start from) with ``overrides`` (field names of :class:`TransformConfig`) applied."""
    if isinstance(base, str):
        if base not in HISTORIES:
            raise KeyError(f"unknown transforms history layout {base!r}; choose one of {list(HISTORIES)} or pass a "
                           f"TransformConfig")
        base = HISTORIES[base]
    elif not isinstance(base, TransformConfig):
        raise TypeError(f"transform_config takes a history layout's name {list(HISTORIES)} or a TransformConfig, got "
                        f"{base!r}")
    fields = {f.name for f in dataclasses.fields(TransformConfig)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise TypeError(f"unknown transform option(s) {unknown}; valid options: {sorted(fields)}")
    return dataclasses.replace(base, **overrides)


@dataclass
class RewardWeights:
    """The weight of each of the 13 reference reward terms (``transforms.reward_weights``; on the command line
    ``--transforms.reward_weights.body_vel 0.9``). ``None`` keeps the term's reference weight (in brackets below,
    ``reward_terms.REFERENCE_TERMS``); a number replaces it. The default triples the velocity-tracking term."""

    orientation: float | None = None
    """neck orientation, weight · exp(-s·|θ_neck|) (reference 0.3); None: the reference weight"""
    qpos: float | None = None
    """joint positions against the reference walk (reference 0.35); None: the reference weight"""
    qvel: float | None = None
    """joint velocities, weight · exp(-s·‖q̇‖²) (reference 0.05); None: the reference weight"""
    body_vel: float | None = 0.9
    """pelvis velocity against the command (reference 0.3); None: the reference weight"""
    contact_force: float | None = None
    """foot contact forces (reference 0.1); None: the reference weight"""
    torque: float | None = None
    """leg torques (reference 0.05); None: the reference weight"""
    torque_diff: float | None = None
    """change of the leg torques between steps (reference 0.6); None: the reference weight"""
    qacc: float | None = None
    """joint accelerations (reference 0.05); None: the reference weight"""
    foot_contact: float | None = None
    """feet in contact when the reference walk has them so (reference 0.2); None: the reference weight"""
    contact_force_diff: float | None = None
    """change of the foot contact forces (reference 0.2); None: the reference weight"""
    force_ref: float | None = None
    """foot forces against the reference's (reference 0.2); None: the reference weight"""
    force_threshold: float | None = None
    """foot force over its threshold, a penalty (reference -0.08); None: the reference weight"""
    force_diff_threshold: float | None = None
    """foot force change over its threshold, a penalty (reference -0.05); None: the reference weight"""

    def as_map(self) -> dict[str, float]:
        """``{term: weight}`` of the terms given a weight (what :class:`TransformConfig` takes); raises
        ``ValueError`` naming a weight that is not a finite number."""
        weights = {}
        for name in REFERENCE_TERM_NAMES:
            value = getattr(self, name)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"transforms.reward_weights.{name} must be a finite number (or None for the "
                                 f"reference weight), got {value!r}")
            weights[name] = float(value)
        return weights


@dataclass
class TransformSettings:
    """The transforms section of the run config tree (``RunConfig.transforms``): the :class:`TransformConfig`
    choices that are plain values, so that they can be saved with a checkpoint and given on the command line.

    The fields' docstrings are the command line's help (``recipes/ppo_walk.py --help``).
    """

    history: str = "reference"
    """observation + action history layout: reference (5 observations every 2 steps, 4 actions) or tocabilab (the
    last 5 observations and 4 actions)"""
    observation: str = "reference"
    """per-step observation: reference (37 values: pelvis roll, pitch, yaw, leg joints, phase, command, foot F/T) or
    base_vel (those and the pelvis's linear and angular velocity in its own frame, 43 values)"""
    reward_weights: RewardWeights = field(default_factory=RewardWeights)
    """the weight of each reward term"""
    normalization: str = "fixed"
    """observation normalisation: fixed (the reference statistics), running or none"""
    obs_clip: float | None = None
    """clip of the normalised observation; None: no clip"""
    zero_reward_on_terminated: bool = True
    """reward and terms are 0 on a terminating step"""
    compile_reward: bool = False
    """torch.compile the reward terms (not with a captured env step)"""
    sensor_noise: SensorNoiseConfig = field(default_factory=SensorNoiseConfig)
    """sensor biases and noise on the observation (all 0: none; SensorNoiseConfig.tocabi_lab(): the TOCABI lab's)"""
    body_vel_scale: float | None = None
    """sharpness s of the velocity-tracking term body_vel, weight·exp(-s·‖v − cmd‖²) [s²/m²] (reference 3.0: a
    0.1 m/s error then costs 3 % of the term); None: the reference's"""
    heading_weight: float = 0.0
    """weight w of the heading-hold term heading, w·exp(-s·ψ²), ψ the pelvis yaw from the episode's start heading
    [rad] (not a reference term: reward_terms.HeadingHold); 0: off"""
    heading_scale: float = 20.0
    """sharpness s of the heading-hold term [1/rad²] (20: a 0.1 rad turn costs 18 % of the term)"""
    cycle_vel_weight: float = 0.0
    """weight w of the cycle-mean velocity term cycle_vel, w·exp(-s·‖ē‖²), ē the velocity-tracking error averaged
    over the last gait cycle [m/s] (not a reference term: reward_terms.CycleVelTracking; needs
    env.task.cycle_velocity); 0: off"""
    cycle_vel_scale: float = 100.0
    """sharpness s of the cycle-mean velocity term [s²/m²] (100: a 0.05 m/s average error costs 22 % of the term,
    0.1 m/s 63 %)"""
    foot_gap_weight: float = 0.0
    """weight w of the foot-gap term foot_gap, w·exp(-(max(g − d, 0)/0.05 m)²), d the feet's sideways distance in
    the heading frame [m] (not a reference term: reward_terms.FootGap; touching feet end the episode); 0: off"""
    foot_gap_min: float = 0.24
    """distance g [m] between the Foot_Link origins from which the foot-gap term pays in full (the reference walk
    keeps 0.25 m; the 0.17 m wide soles, 0.145 m below the origins, touch nearer than that when tilted)"""
    kick_relax: KickRelax = field(default_factory=KickRelax)
    """reward terms (the reference gait's clocked joint positions, contacts and loads, and smoothness) scaled down
    for seconds after a kick (env.pushes) while the robot recovers; seconds 0: off"""

    def reward_weight_map(self) -> dict[str, float]:
        """``reward_weights`` as ``{term: weight}`` of the terms given one; raises ``ValueError`` naming a bad one."""
        if not isinstance(self.reward_weights, RewardWeights):
            raise ValueError(f"transforms.reward_weights must be a RewardWeights (one weight per term, e.g. "
                             f"RewardWeights(body_vel=0.9)), got {self.reward_weights!r}")
        return self.reward_weights.as_map()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad option and the accepted values."""
        if self.history not in HISTORIES:
            raise ValueError(f"unknown transforms.history {self.history!r}; choose one of {list(HISTORIES)}")
        if self.observation not in OBS_LAYOUTS:
            raise ValueError(f"unknown transforms.observation {self.observation!r}; choose one of {list(OBS_LAYOUTS)}")
        if self.normalization not in NORMALIZATIONS:
            raise ValueError(f"transforms.normalization must be one of {NORMALIZATIONS}, got {self.normalization!r}")
        self.reward_weight_map()
        if self.obs_clip is not None and not (self.obs_clip > 0 and math.isfinite(self.obs_clip)):
            raise ValueError(_CLIP_NOT_POSITIVE.format(prefix="transforms.", clip=self.obs_clip))
        if self.obs_clip is not None and self.normalization == "none":
            raise ValueError(_CLIP_WITHOUT_NORMALIZATION.format(prefix="transforms.", clip=self.obs_clip))
        for name, kind in (("sensor_noise", SensorNoiseConfig), ("kick_relax", KickRelax)):
            _section(getattr(self, name), kind, f"transforms.{name}", dicts=False)  # the tree converts dicts
        self.sensor_noise.validate()
        self.kick_relax.validate()
        if self.kick_relax.enabled:
            in_use = (*REFERENCE_TERM_NAMES, *self.extra_terms())
            missing = [t for t in self.kick_relax.terms if t not in in_use]
            if missing:
                raise ValueError(f"transforms.kick_relax.terms names {missing}, which no reward term in use is "
                                 f"called (terms in use: {list(in_use)}); name terms in use, or switch the term on "
                                 "with its weight (e.g. transforms.heading_weight)")
        if self.body_vel_scale is not None and (isinstance(self.body_vel_scale, bool) or not isinstance(
                self.body_vel_scale, (int, float)) or not 0 < self.body_vel_scale < math.inf):
            raise ValueError(f"transforms.body_vel_scale must be a finite number > 0 (s in exp(-s·‖v − cmd‖²), "
                             f"s²/m²) or none for the reference's 3.0, got {self.body_vel_scale!r}")
        for name, low, term in (("heading_weight", "0 <=", "the heading-hold term w·exp(-s·ψ²)"),
                                ("heading_scale", "0 <", "the heading-hold term w·exp(-s·ψ²)"),
                                ("cycle_vel_weight", "0 <=", "the cycle-mean velocity term w·exp(-s·‖ē‖²)"),
                                ("cycle_vel_scale", "0 <", "the cycle-mean velocity term w·exp(-s·‖ē‖²)"),
                                ("foot_gap_weight", "0 <=", "the foot-gap term w·exp(-(max(g − d, 0)/0.05)²)"),
                                ("foot_gap_min", "0 <", "the foot-gap term's g [m]")):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not (
                    value >= 0 if low == "0 <=" else value > 0):
                raise ValueError(f"transforms.{name} must be a finite number with {low} value ({term}), got "
                                 f"{value!r}")

    def extra_terms(self) -> tuple[str, ...]:
        """The names of the terms beyond the reference's that these settings switch on (their weight > 0)."""
        weights = (("heading", self.heading_weight), ("cycle_vel", self.cycle_vel_weight),
                   ("foot_gap", self.foot_gap_weight))
        return tuple(name for name, weight in weights if isinstance(weight, (int, float)) and weight > 0)

    def extra_reward_terms(self) -> tuple:
        """The reward terms beyond the reference's that these settings switch on (their weight > 0), as the
        ``RewardTerm`` objects :meth:`transform_config` adds: ``HeadingHold``, ``CycleVelTracking``, ``FootGap``
        (``reward_terms``; imports torch). What to add to a ``reward_terms`` list of one's own to keep them."""
        if not self.extra_terms():
            return ()
        # Imported here: the terms need torch, which reading the config tree does not.
        from tocabi_torchrl.transforms.reward_terms import CycleVelTracking, FootGap, HeadingHold

        extra = []
        if self.heading_weight > 0:
            extra.append(HeadingHold(weight=float(self.heading_weight), scale=float(self.heading_scale)))
        if self.cycle_vel_weight > 0:
            extra.append(CycleVelTracking(weight=float(self.cycle_vel_weight), scale=float(self.cycle_vel_scale)))
        if self.foot_gap_weight > 0:
            extra.append(FootGap(weight=float(self.foot_gap_weight), min_gap=float(self.foot_gap_min)))
        return tuple(extra)

    def transform_config(self, **overrides) -> TransformConfig:
        """The :class:`TransformConfig` these settings select, with ``overrides`` (its field names) on top.
        ``reward_weights`` and ``reward_scales`` given here set the named terms on top of these settings' own
        weights and scales (the default's ``body_vel`` weight 0.9 stays unless named); with ``reward_terms`` given,
        the settings' own apply to the terms among them. ``max_episode_steps`` is ``None`` unless overridden: the
        env is the truncation clock.

        ``reward_terms`` replaces the terms, and must hold each term beyond the reference's that these settings
        switch on (:meth:`extra_reward_terms`, e.g. the robust preset's heading and foot_gap), or a term of that
        name: ``ValueError`` naming the ones left out, so that a list does not silently drop them. Keep them with
        ``reward_terms=(..., *settings.extra_reward_terms())``, or set their weights (``heading_weight``,
        ``cycle_vel_weight``, ``foot_gap_weight``) to 0 to leave them out."""
        self.validate()
        weights = self.reward_weight_map()
        scales = {} if self.body_vel_scale is None else {"body_vel": float(self.body_vel_scale)}
        # A term that is off is not added, so a config without it computes what it always did.
        extra = self.extra_reward_terms()
        if overrides.get("reward_terms") is not None:
            # Terms without body_vel once ended in "weights given for unknown term(s) ['body_vel']", a weight the
            # caller never gave: these settings' own weights and scales only reach the built-in terms named in use. A
            # term object keeps its own (a term of one's own named body_vel once got the setting's 0.9).
            in_use = {t for t in overrides["reward_terms"] if isinstance(t, str)}
            weights = {name: w for name, w in weights.items() if name in in_use}
            scales = {name: v for name, v in scales.items() if name in in_use}
            _check_extra_terms_kept(extra, overrides["reward_terms"])
        # On top, not instead: {"qpos": 0.5} replacing the map silently put body_vel back to the reference's 0.3
        # (weights), and the robust preset's body_vel sharpness 8.0 back to 3.0 (scales).
        weights.update(overrides.pop("reward_weights", None) or {})
        scales.update(overrides.pop("reward_scales", None) or {})
        values = dict(obs_layout=OBS_LAYOUTS[self.observation], normalization=self.normalization,
                      obs_clip=self.obs_clip, zero_reward_on_terminated=self.zero_reward_on_terminated,
                      compile_reward=self.compile_reward,
                      reward_weights=weights, max_episode_steps=None, sensor_noise=self.sensor_noise,
                      kick_relax=self.kick_relax, reward_scales=scales)
        if extra:
            values["reward_terms"] = (*REFERENCE_TERM_NAMES, *extra)
        return transform_config(self.history, **{**values, **overrides})


#: The settings' weight of each term beyond the reference's, by the term's name (for the messages).
_EXTRA_WEIGHTS = {"heading": "heading_weight", "cycle_vel": "cycle_vel_weight", "foot_gap": "foot_gap_weight"}


def _check_extra_terms_kept(extra: Sequence, given) -> None:
    """Raise ``ValueError`` if the ``reward_terms`` list ``given`` leaves out a term of ``extra`` (the settings'
    terms beyond the reference's) and holds no term of its name: a given list replaces every term, and the settings'
    extra terms were silently dropped."""
    names = {t if isinstance(t, str) else getattr(t, "name", getattr(t, "__name__", None)) for t in given}
    dropped = [t for t in extra if t.name not in names]
    if not dropped:
        return
    switches = ", ".join(f"transforms.{_EXTRA_WEIGHTS[t.name]} {t.weight:g}" for t in dropped)
    raise ValueError(
        f"reward_terms replaces the reward terms and leaves out {[t.name for t in dropped]}, which these transform "
        f"settings switch on ({switches}): to keep them, add them to reward_terms ({', '.join(map(repr, dropped))}; "
        "TransformSettings.extra_reward_terms() gives them as configured); to leave them out, set those weights to 0 "
        "in the settings (with make_env's preset=, pass config= and transforms= of "
        "tocabi_torchrl.config.preset_tree(preset) with the weights changed instead)")
