# The project's GPU checks on a lent device machine: per-posterior seconds, the GPU tests, render speed.
# Prepare first (here, on the CPU): python scripts/gpu/prepare_devdata.py DATASET MODEL  (writes .devdata/; the
# Mitsuba and Dr.Jit wheels stripped to the rgb variants go in .devdata/site.tar.xz, wheels of the rest in .whl/).
# Run there: bash scripts/gpu/device_run.sh  ($OUT collects the outputs). The newest question first: a call has
# 600 s, and the parts after it are cut where it runs out.
export PYTHONUNBUFFERED=1
mkdir -p /tmp/site && tar -xJf .devdata/site.tar.xz -C /tmp/site || exit 1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee $OUT/gpu.txt
python3 -m mitsuba_p3.cli doctor 2>&1 | tee $OUT/doctor.txt
echo "== bench_posterior (the JAX tracer: each plain SMC step on the host, then as one compiled call on the device)"
timeout 240 python3 scripts/bench_posterior.py .devdata/model .devdata/images/*.png --renderer jax --particles 64 --seeds 2 \
  --steps host,device --truth .devdata/images/truth.json --profile $OUT/profile_steps.txt \
  > $OUT/bench_posterior_steps.json 2> $OUT/bench_posterior_steps.err; tail -5 $OUT/bench_posterior_steps.err
echo "== tests on the GPU (render, gradients, JAX tracer, backend, Mitsuba inside JAX in place, the SMC step on the device)"
timeout 200 python3 -m pytest -q -p no:cacheprovider -o addopts="" -m "not slow" tests/test_backend.py tests/test_render.py \
  tests/test_gradients.py tests/test_jax_tracer.py tests/test_render_functions.py \
  tests/test_infer.py::test_a_step_on_the_device_is_the_host_steps_reweight_resample_and_move 2>&1 | tee $OUT/tests_gpu.txt | tail -40
echo "== bench_render"
timeout 100 python3 scripts/bench_render.py --renderers mitsuba,jax --repeats 10 --wide 20,256,4096 --callbacks 128,512,4096 > $OUT/bench_render_h200.json 2> $OUT/bench_render.err; tail -3 $OUT/bench_render.err
echo "== bench_posterior (Mitsuba cuda_ad_rgb, 6 images)"
timeout 170 python3 scripts/bench_posterior.py .devdata/model .devdata/images/0[0-5].png --renderer mitsuba --particles 64,256 \
  --truth .devdata/images/truth.json > $OUT/bench_posterior_h200_mitsuba.json 2> $OUT/bench_posterior.err; tail -5 $OUT/bench_posterior.err
