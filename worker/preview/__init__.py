"""Looking at a dataset: the contact sheet (`seasynth preview`), the sonar waterfall, and the playground's renders."""
