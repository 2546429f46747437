"""Planning a run before renting the pod: the same step train.py compiles, measured.

  planner     `train.py --compile_only` and benchmarks/train_step.py: compile the step for a
              target, memory per chip, step time, days, the launch lines
  flops       the step's FLOPs counted on its jaxpr, and the analytic count by part
  hlo_stats   collectives and their bytes read off the compiled HLO
  topologies  accelerator slices by their Cloud names (v5e-8, v5p-128, ...) and their chips

Depends on training (the step it plans) and below; nothing in the library depends on it.
"""
