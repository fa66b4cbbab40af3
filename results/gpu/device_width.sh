# Use the width (issue 44, item 3): the default SMC against 8x its particles on a lent GPU, 20 evenly
# spaced fsclvr *train* images under two seeds each; the JAX tracer end to end (no Mitsuba).
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee $OUT/gpu.txt
timeout 300 python3 scripts/bench_posterior.py .devdata/model .devdata/train/[0-9][0-9].png --renderer jax \
  --particles 64,512 --seeds 2 --truth .devdata/train/truth.json > $OUT/bench_width.json 2> $OUT/width.err
grep '^{"' $OUT/bench_width.json; tail -2 $OUT/width.err
