"""The tracker (cost, optimizers, Algorithm 1), its evaluation, and the `inhand-tracker` command."""
