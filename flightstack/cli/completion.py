"""`flightstack completion {bash,zsh,fish}`: the shell code that makes the shell complete `flightstack`'s
subcommands and options through argcomplete (docs/getting-started.md):

    eval "$(flightstack completion bash)"        # in ~/.bashrc
    eval "$(flightstack completion zsh)"         # in ~/.zshrc, after compinit
    flightstack completion fish | source         # in ~/.config/fish/config.fish

The shell code calls `flightstack` with argcomplete's environment variables set; `main` then answers
with the completions (argcomplete.autocomplete, before parsing) and exits without running anything."""

from __future__ import annotations

import argparse
import sys

import argcomplete

SHELLS = ("bash", "zsh", "fish")


def cmd_completion(args: argparse.Namespace) -> int:
    """Print the completion code of `flightstack` for args.shell."""
    code = argcomplete.shellcode(["flightstack"], shell=args.shell)
    sys.stdout.write(code if code.endswith("\n") else code + "\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add `completion` to the top-level subcommands."""
    c = sub.add_parser(
        "completion",
        description='Shell completion: eval "$(flightstack completion bash)" in ~/.bashrc; the same with zsh '
        "in ~/.zshrc (after compinit); `flightstack completion fish | source` in fish's config.fish.",
    )
    c.add_argument("shell", choices=SHELLS, help="the shell to print the code for")
    c.set_defaults(func=cmd_completion)
