"""Command-line interface: ``lungdeform COMMAND``. Only this package prints or picks exit codes."""
