"""`python -m seasynth.cli`: the same as the `seasynth` command."""

from seasynth.cli.main import main

if __name__ == "__main__":
    main()
