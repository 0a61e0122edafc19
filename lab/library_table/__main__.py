"""``python -m lab.library_table ...``: the per-library table (:mod:`lab.library_table.table`)."""

from lab.library_table.table import main

if __name__ == "__main__":
    main()
