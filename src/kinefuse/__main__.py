"""``python -m kinefuse``: the same as the ``kinefuse`` console script."""

from kinefuse.cli import main

if __name__ == "__main__":
    main()
