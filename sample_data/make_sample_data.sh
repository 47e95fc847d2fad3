#!/usr/bin/env bash
# Regenerate every file in sample_data/ (run from the repository root).
# The simulator is deterministic given --seed, so the files come out identical.
set -euo pipefail
cd "$(dirname "$0")"

# REEP's main example: three-sine dither, f0 70 kHz -> 69.65 kHz and Q 200 -> 90 at t = 30 ms.
afmtool simulate ltv -o ltv_step.h5 --seed 1 \
  --set duration_s=0.05 --set step_time_s=0.03 --set step_f0_hz=69650.0 --set step_q=90.0

# The same capture in every other format (CSV and bags carry no /truth).
afmtool convert ltv_step.h5 ltv_step.csv
afmtool convert ltv_step.h5 ltv_step.bag
rm -rf ltv_step_mcap && afmtool convert ltv_step.h5 ltv_step_mcap --format ros2-mcap

# A tapping-mode force curve (attractive force set of thesis §3.4.3, f0 80,318 Hz, Q 168).
afmtool simulate tapping -o tapping_force_curve.h5 --seed 2 \
  --set duration_s=0.06 --set program=force-curve --set force_set=attractive \
  --set separation_nm=30.0 --set turn_separation_nm=2.0 --set amplitude_nm=20.0
