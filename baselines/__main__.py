"""``python -m baselines train ...``: the same command as ``offdyn-bench train``."""

import typer

from baselines.cli import train_command

app = typer.Typer(add_completion=False, no_args_is_help=True)


@app.callback()
def baselines() -> None:
    """Reference baselines of offdyn-bench."""


app.command("train")(train_command)

if __name__ == "__main__":
    app()
