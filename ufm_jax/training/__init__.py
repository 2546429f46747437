"""Training: what train.py wires together.

  trainer          model, input, loss, the jitted train step, predictions for the evaluators
  config_lib       helpers of the configs/ recipes (argument parsing, typed unset keys)
  model_init       the init path: random, released DINOv2 / UFM weights, a bootstrap checkpoint
  optim            AdamW, the official learning-rate schedules and parameter groups
  losses           the official loss terms and a recipe's sum of terms (loss_common: masked means)
  refine_training  the refinement recipe's classification loss and its pixel cap
  distill          distillation in the step (teacher: loading the teacher; distill_loss: its terms)
  accumulation     gradient accumulation over microbatches
  sharding         the config's mesh and partitioning rules as NamedShardings (the one home)
  loop_control     preemption, stop and checkpoint decisions of the loop

Depends on runtime, official, data and models; the evaluators and the planner build on it.
"""
