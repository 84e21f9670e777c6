#!/bin/sh
# Test double of `streetsim train --log LOG --out DIR [--preset P] [--set NAME=VALUE]... [--resume]`
# for the training-job tests (--set iterations=N: N iterations, --set seed=S). The config's flags
# (server/training_config.cc) but those two are appended, one line per run, to DIR/flags. Prints the trainer's progress lines on stderr, one per iteration, keeps a
# "checkpoint" (DIR/checkpoint.bin = last iteration, replaced by rename) and on --resume continues from it (noted in
# DIR/resumed). LOG/train_sleep_s: pause per iteration; LOG/train_fail: exit 5; LOG/preview.png:
# copied to DIR/preview/ (as the trainer's held-out previews). Leaves
# DIR/scene.ply (from init) as it is and writes DIR/trained. LOG/train_kill_at K: a run that did
# not resume kills itself with SIGKILL after its K-th iteration's checkpoint (a trainer killed from
# outside); with LOG/train_kill_every_run, every run kills itself after its first iteration.
# LOG/train_progress_once: only the first iteration's progress line is printed (a real trainer
# prints every few iterations, so its last line can lag the end).
set -e
log=""; out=""; n=0; resume=0; seed=""; flags=""; field=static
while [ $# -gt 0 ]; do
  case "$1" in
    --log) log="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --iterations) n="$2"; shift 2 ;;
    --seed) seed="$2"; shift 2 ;;
    --resume) resume=1; shift ;;
    --preset) flags="$flags $1 $2"; shift 2 ;;
    --set)
      case "$2" in
        iterations=*) n="${2#iterations=}" ;;
        seed=*) seed="${2#seed=}" ;;
        field=*) field="${2#field=}"; flags="$flags $1 $2" ;;
        *) flags="$flags $1 $2" ;;
      esac
      shift 2 ;;
    --field) field="$2"; flags="$flags $1 $2"; shift 2 ;;
    --field-modules|--static-iterations|--resolution-scale|--low-res-scale|--low-res-iterations|\
    --holdout-every|--clip-frames|--clip-overlap|--field-lr-scale|--field-lr-decay-iterations|--backend)
      flags="$flags $1 $2"; shift 2 ;;
    *) echo "fake train: unknown flag $1" >&2; exit 2 ;;
  esac
done
echo "${flags# }" >> "$out/flags"
# The real trainer's last line on a failure is "streetsim train: <why>".
if [ -f "$log/train_fail" ]; then echo "streetsim train: failing as asked" >&2; exit 5; fi
i=0
if [ "$resume" = 1 ] && [ -f "$out/checkpoint.bin" ]; then
  i=$(cat "$out/checkpoint.bin")
  echo "$i" >> "$out/resumed"
fi
pause=0
if [ -f "$log/train_sleep_s" ]; then pause=$(cat "$log/train_sleep_s"); fi
while [ "$i" -lt "$n" ]; do
  i=$((i + 1))
  sleep "$pause"
  echo "I1122 12:00:00.000 trainer.cc:1] a log line that is not progress" >&2
  if [ ! -f "$log/train_progress_once" ] || [ "$i" -eq 1 ]; then
  printf '[####..........] %d/%d  loss %d.%04d  psnr %d.50 dB  4000 Gaussians  12.50 it/s  ETA 0:00:%02d\n' \
    "$i" "$n" 0 "$((1000 - i))" "$((20 + i))" "$((n - i))" >&2
  fi
  # Atomic like the real trainer's: a stop between truncate and write must not lose the count.
  echo "$i" > "$out/checkpoint.bin.tmp"
  mv "$out/checkpoint.bin.tmp" "$out/checkpoint.bin"
  if [ "$resume" = 0 ] && [ -f "$log/train_kill_at" ] && [ "$i" -eq "$(cat "$log/train_kill_at")" ]; then
    kill -9 $$
  fi
  if [ -f "$log/train_kill_every_run" ]; then kill -9 $$; fi
done
if [ -f "$log/preview.png" ]; then
  mkdir -p "$out/preview"; cp "$log/preview.png" "$out/preview/heldout_frame0001_cam0.png"
fi
# Held-out metrics as the trainer leaves them: LOG/heldout.json -> DIR/heldout.json; LOG/clips/
# (clips.json, clip_000/heldout.json ...) -> a clip set (DIR/clips.json and its clip directories).
if [ -f "$log/heldout.json" ]; then cp "$log/heldout.json" "$out/heldout.json"; fi
if [ -d "$log/clips" ]; then cp -r "$log/clips/." "$out/"; fi
echo "iterations $n${seed:+ seed $seed}" > "$out/trained"
echo "{\"iterations\": $n, \"background\": [0, 0, 0], \"resolution_scale\": 1.0, \"holdout_every\": 4, \"field\": \"$field\"}" > "$out/train_meta.json"
echo "streetsim train: $n iterations, 4000 Gaussians -> $out/scene.ply" >&2
