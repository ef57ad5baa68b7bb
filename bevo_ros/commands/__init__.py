"""The ``bevo`` commands, one module each (``bevo_ros.cli`` runs them): ``build_parser()`` and
``main(argv) -> int``; argument parsing and messages only, the work is done by the package."""
