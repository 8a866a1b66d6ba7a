"""The edge of the `contact-viz` command group: every command's bad input ends as one line.

Kept apart from cli.py (the commands) so that the edge is one small unit: the group class the
typer app is made with. What counts as bad input and how it reads is decided in
contact_viz.console.describe_error.
"""

from __future__ import annotations

import typer
from typer.core import TyperGroup


class EdgeGroup(TyperGroup):
    """Bad input that reaches the edge (an OSError, SessionError, ValueError, gRPC error) is one line,
    ``error: PATH: what was expected``, and exit status 2; --verbose shows the traceback."""

    def format_commands(self, ctx, formatter) -> None:
        """The command list with each command's whole first sentence, wrapped (click cuts it with "...")."""
        import inspect

        rows = [(name, " ".join(inspect.cleandoc(command.help or "").split("\n\n")[0].split()))
                for name in self.list_commands(ctx)
                if (command := self.get_command(ctx, name)) is not None and not command.hidden]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)

    def invoke(self, ctx):
        from contact_viz import console

        try:
            return super().invoke(ctx)
        except (typer.Exit, typer.Abort, typer.TyperException):  # usage errors, exits: typer prints them
            raise
        except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP (console.stop_on_signals)
            line, status = console.stop_line(exc)
            _say(line)
            console.stop_reported()
            raise typer.Exit(code=status) from None
        except Exception as exc:  # noqa: BLE001 - sorted by describe_error; bugs keep their traceback
            line = console.describe_error(exc)
            if line is None or console.VERBOSE:
                raise
            _say(f"error: {line}", fg=typer.colors.RED)
            raise typer.Exit(code=2) from None


def _say(line: str, **style) -> None:
    """The one line on stderr; a terminal that has gone (SIGHUP, a closed pipe) does not turn it into a traceback."""
    try:
        typer.secho(line, err=True, **style)
    except OSError:
        pass
