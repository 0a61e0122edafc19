"""The model_based preset's residual gain: survival under random residuals, the gain at the torque limits vs at the
PD-residual modes' authority (0.5 rad × the robot's Kp), beside pd_reference under the same noise. C MuJoCo.

Wrote residual_gain.json (docs/training.md), ~4 min on 2 cores (an existing file is never replaced):
``PYTHONPATH=. python lab/analysis/mb_residual_gain.py docs/training/model_based/residual_gain.json``
"""
from tocabi_torchrl.envs.config import MB_RESIDUAL_GAIN_PD

from lab.analysis.mb_zero_action import out_path, run, write  # same rollout, same seeds


def main(argv=None) -> dict:
    out = out_path(__doc__, argv)
    cases = [("pd_reference", dict(control_mode="pd_reference")),
             ("model_based, g = torque limits", dict(control_mode="model_based")),
             ("model_based, g = 0.5 rad x robot Kp",
              dict(control_mode="model_based", mb_residual_gain=MB_RESIDUAL_GAIN_PD))]
    results = []
    for std in (0.05, 0.2):
        for name, kw in cases:
            results.append({"case": name, "residual_std": std, "steps": 1000, "num_envs": 16,
                            **run(std, 1000, 16, **kw)})
            print(results[-1], flush=True)
    doc = {"what": "leg actions N(0, std) per step, phase action 0; C MuJoCo on the CPU, TocabiWalk(seed=0), default "
                   "command schedule, episodes never truncated; a pd_reference action unit is 0.5 rad of target",
           "results": results}
    write(out, doc)
    return doc


if __name__ == "__main__":
    main()
