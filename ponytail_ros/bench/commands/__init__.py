"""The subcommands of ``ponytail_bench``, one module each.

Each defines ``HELP`` (its line in ``--help``) and ``run(prof, out, meta, log)``: ``prof`` is a
profile (``bench/profiles.py``), ``out`` the output directory, ``meta`` the run metadata stored
in every table (``tables.make_meta``), ``log`` prints progress. ``run`` writes its tables into
``out`` and returns its rows. ``cli.COMMANDS`` registers them.
"""
