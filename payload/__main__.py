"""``python -m payload``: the same command line as the ``payload`` console script."""

from payload.cli import run

if __name__ == "__main__":
    run()
