"""The model_based preset's residual gain: survival under random residuals, the gain at the torque limits vs at the
PD-residual modes' authority (0.5 rad × the robot's Kp), beside pd_reference under the same noise. C MuJoCo.

Wrote residual_gain.json (docs/training.md), ~4 min on 2 cores:
``PYTHONPATH=. python lab/analysis/mb_residual_gain.py docs/training/model_based/residual_gain.json``
"""
import json
import subprocess
import sys
from tocabi_torchrl.envs.config import MB_RESIDUAL_GAIN_PD
from zero_action import run  # this folder's script: same rollout, same seeds

cases = [("pd_reference", dict(control_mode="pd_reference")),
         ("model_based, g = torque limits", dict(control_mode="model_based")),
         ("model_based, g = 0.5 rad x robot Kp",
          dict(control_mode="model_based", mb_residual_gain=MB_RESIDUAL_GAIN_PD))]
results = []
for std in (0.05, 0.2):
    for name, kw in cases:
        results.append({"case": name, "residual_std": std, "steps": 1000, "num_envs": 16, **run(std, 1000, 16, **kw)})
        print(results[-1], flush=True)
commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
doc = {"what": "leg actions N(0, std) per step, phase action 0; C MuJoCo on the CPU, TocabiWalk(seed=0), default "
               "command schedule, episodes never truncated; a pd_reference action unit is 0.5 rad of target",
       "commit": commit, "results": results}
open(sys.argv[1], "w").write(json.dumps(doc, indent=1) + "\n")
