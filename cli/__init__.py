"""The `seasynth` command: the composition root. Each command imports its adapter (worker/, api/, bench/) when
it runs, so `serve` never loads OpenGL and `generate` never loads the web stack; nothing in the domain imports
this package. Commands live by kind: datasets.py (generate .. fetch), servers.py (serve, worker, playground,
reconcile), bench.py (`seasynth bench ...`); app.py holds what they share, main.py the entry point."""
