#!/usr/bin/env bash
# Regenerate every file in sample_data/ (run from the repository root).
# The simulator is deterministic given --seed, so the files come out identical.
set -euo pipefail
cd "$(dirname "$0")"

# REEP's main example: three-sine dither, f0 70 kHz -> 69.65 kHz and Q 200 -> 90 at t = 30 ms.
# Made before issue 14, with the dither held per sample (drive_hold=zoh; the default is now continuous).
afmtool simulate ltv -o ltv_step.h5 --seed 1 --set drive_hold=zoh \
  --set duration_s=0.05 --set step_time_s=0.03 --set step_f0_hz=69650.0 --set step_q=90.0

# The same capture in every other format (CSV and bags carry no /truth).
afmtool convert ltv_step.h5 ltv_step.csv
afmtool convert ltv_step.h5 ltv_step.bag
rm -rf ltv_step_mcap && afmtool convert ltv_step.h5 ltv_step_mcap --format ros2-mcap

# A tapping-mode force curve (attractive force set of thesis §3.4.3, f0 80,318 Hz, Q 168).
afmtool simulate tapping -o tapping_force_curve.h5 --seed 2 \
  --set duration_s=0.06 --set program=force-curve --set force_set=attractive \
  --set separation_nm=30.0 --set turn_separation_nm=2.0 --set amplitude_nm=20.0

# Probe-storage read-back (thesis §7.6): 4 nm bits at 30 kHz under a lever actuated at 100 kHz, 2 ms nominal
# segment first; gzip keeps it small.
afmtool simulate bits -o bits_30khz.raw.h5 --seed 7 --set duration_s=0.012 --set bit_rate_hz=30000.0
afmtool convert bits_30khz.raw.h5 bits_30khz.h5 --compression gzip && rm bits_30khz.raw.h5

# The thermal-sensor sweeps of thesis §6.6.1 for 'identify gamma': a repeated V_sub chirp (100 Hz-150 kHz)
# near the sample (t_s0 = 100 nm) and the same sweep with the tip in contact (the feed-through), gzip HDF5.
afmtool simulate thermal-sweep -o thermal_sweep_near.tmp.h5 --seed 61 \
  --set duration_s=0.1 --set sample_rate_hz=500000.0 --set start_hz=100.0 --set stop_hz=150000.0 \
  --set chirp_repeats=4 --set store_truth=false
afmtool convert thermal_sweep_near.tmp.h5 thermal_sweep_near.h5 --compression gzip && rm thermal_sweep_near.tmp.h5
afmtool simulate thermal-sweep -o thermal_sweep_contact.tmp.h5 --seed 62 \
  --set duration_s=0.1 --set sample_rate_hz=500000.0 --set start_hz=100.0 --set stop_hz=150000.0 \
  --set chirp_repeats=4 --set store_truth=false --set contact=true
afmtool convert thermal_sweep_contact.tmp.h5 thermal_sweep_contact.h5 --compression gzip && rm thermal_sweep_contact.tmp.h5

# A closed-loop raster scan of the calibration grating at 30 Hz (thesis ch. 2): switching-gain
# z-control driven by the in-loop reliability index, contact and force truth; gzip keeps it small.
# Made before issue 14, with the dither held per sample (drive_hold=zoh; the default is now continuous).
afmtool simulate raster -o raster_grating_raw.h5 --seed 4 --set drive_hold=zoh \
  --set line_rate_hz=30.0 --set lines=3 --set pixels_per_line=32
afmtool convert raster_grating_raw.h5 raster_grating.h5 --compression gzip && rm raster_grating_raw.h5

# A force curve at the thesis's rate for 'kalman-bank' (§3.4.3 attractive set: f0 80,318 Hz, Q 168,
# 0.4 s, side lines at a quarter): slow enough that REEP's window spans well under a 0.5 nm bin.
afmtool simulate tapping -o force_curve_thesis_raw.h5 --seed 1 \
  --set duration_s=0.4 --set f0_hz=80318.0 --set q=168.0 --set force_set=attractive \
  --set program=force-curve --set separation_nm=30.0 --set turn_separation_nm=2.0 \
  --set amplitude_nm=20.0 --set sideband_scale=0.25
afmtool convert force_curve_thesis_raw.h5 force_curve_thesis.h5 --compression gzip && rm force_curve_thesis_raw.h5
