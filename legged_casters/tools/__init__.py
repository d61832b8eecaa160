"""The command-line tools behind train.py, play.py and export.py.

common: errors and exit codes, log folders, run and checkpoint selection, loading
checkpoints safely. train / play / export: one module per command, each with a
`main(argv)` that returns the process exit code.
"""
