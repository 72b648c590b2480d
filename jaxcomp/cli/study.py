"""`jaxcomp study`: Monte-Carlo studies over thousands of simulated robots (MJX).

The subcommands live in their own modules and register on the ``study`` group defined here;
the studies themselves are the library ``jaxcomp.studies``.
"""

from jaxcomp.cli.group import cli


@cli.group()
def study() -> None:
    """Monte-Carlo studies on MJX: many simulated robots, each with its own hidden truth.

    Worlds are sharded over every accelerator present (GPUs of one host; CPU with small
    --worlds). A rerun with the same --seed reproduces the numbers exactly.
    """
