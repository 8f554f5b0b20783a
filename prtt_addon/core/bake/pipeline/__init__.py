"""The bake's pipeline: plan, context, stages, commit and runner."""
