"""The dispensing job (automated-dispensing paper): boards, dispensing areas, pixel-to-machine mapping, paths, beads."""
