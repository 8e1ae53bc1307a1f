# Two commands do all set-up on a fresh machine:  `make demo`  and  `make test`.
PY ?= python3
# Extra pip options for torch: empty here (this machine's pip finds a local CPU wheel); elsewhere the CPU build is
# `make test TORCH_PIP="--index-url https://download.pytorch.org/whl/cpu"` (else pip fetches the multi-GB CUDA one)
TORCH_PIP ?=
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test test-slow bench stacked-books stress lint clean

$(BIN)/.installed: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	# torch pinned first (the CPU build; an unpinned torch would download a multi-GB CUDA build)
	$(BIN)/python -m pip install -q $(TORCH_PIP) torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $@

# The Billiards environment (15-ball rack) from its trivial start: 15 iterations on the object ball's distance to
# its pocket after 2 s, plot and GIF; beside it, on the other core, the two short demos (a two-ball shot, a triangle
# pair pulled apart), whose output is shown when the optimisation is done (results/demo/demos.log).
demo: $(BIN)/.installed
	mkdir -p results/demo
	NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 sh -c '$(BIN)/python scripts/demo_billiards.py --out results/demo && \
		$(BIN)/python scripts/demo_pair.py --out results/demo' > results/demo/demos.log 2>&1 & \
	$(BIN)/python scripts/optimize.py --task Billiards --seed 1 --loss final --horizon 200 --knots 10 --iters 15 \
		--lr 0.05 --optimizer adam --threads 1 --out results/demo/billiards_env; rc=$$?; \
	wait $$!; rc2=$$?; cat results/demo/demos.log; \
	[ $$rc -eq 0 ] && [ $$rc2 -eq 0 ]

# one pytest-xdist worker per core, each computing on one thread (tests/conftest.py)
test: $(BIN)/.installed
	$(BIN)/python -m pytest -q -n auto

test-slow: $(BIN)/.installed
	$(BIN)/python -m pytest -q -n auto -m slow

bench: $(BIN)/.installed
	$(BIN)/python -m pip install -q -e '.[bench]'
	$(BIN)/python scripts/bench_pair.py --out results/bench_pair
	$(BIN)/python scripts/bench_contact.py --out results/bench_contact
	$(BIN)/python scripts/bench_step.py --out results/bench_step

stacked-books: $(BIN)/.installed
	$(BIN)/python scripts/stacked_books.py --out results/stacked_books

stress: $(BIN)/.installed
	$(BIN)/python scripts/stress_step.py --out results/stress_step
	$(BIN)/python scripts/stress.py --out results/stress

lint: $(BIN)/.installed
	$(BIN)/ruff check cfd_torch envs tests scripts
	$(BIN)/ruff format --check cfd_torch envs tests scripts

clean:
	rm -rf $(VENV) results
