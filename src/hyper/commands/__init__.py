"""The command layer: `hyper JOB` and `python -m hyper.JOB`; imports the library, never imported by it."""
