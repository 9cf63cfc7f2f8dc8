"""ago_train: data, pseudo-labels, model, losses, training, evaluation (torch).

May import: ago_runtime (never ago_export). Its verb modules (cli.py here and in synth/, pseudo/,
text/, experiments/) import nothing heavy at import time: torch is imported inside the commands.
"""
