# needlecli: common tasks. `make help` lists them.
PY ?= python

STUDIES := results/studies

.PHONY: help install demo test bench lint clean seed003 datasets regress

help:
	@echo "make install  - install needlecli with test extras (editable)"
	@echo "make demo     - run the bundled default experiment and write its tables"
	@echo "make test     - run the test suite (what .ci/run runs)"
	@echo "make bench    - speed benchmarks (figures also as ratios against an in-run reference)"
	@echo "make lint     - ruff"
	@echo "make seed003  - seed 003's simulation study: Table 1, Figs. 6-8 (results and tables in $(STUDIES))"
	@echo "make datasets - rebuild the synthetic logs in datasets/ from configs/datasets/"
	@echo "make regress  - replay every bundled data set and check its tables against datasets/baselines/"
	@echo "make clean    - remove results/ and caches"

install:
	$(PY) -m pip install -e '.[test]'

demo:
	needle simulate configs/default.yaml
	needle evaluate results/default.h5

test:
	$(PY) -m pytest

bench:
	$(PY) benchmarks/bench_simulate.py
	$(PY) benchmarks/bench_ukf.py
	$(PY) benchmarks/bench_observers.py
	$(PY) benchmarks/bench_sweep.py
	$(PY) benchmarks/bench_imaging.py

lint:
	$(PY) -m ruff check needlecli tests benchmarks

clean:
	rm -rf results .pytest_cache .ruff_cache .hypothesis

seed003:
	@for c in table1 fig6 fig7 fig8; do \
	  needle simulate configs/seed003/$$c.yaml --out $(STUDIES)/seed003_$$c.h5 --quiet > /dev/null && \
	  needle evaluate $(STUDIES)/seed003_$$c.h5 --out $(STUDIES)/seed003 || exit 1; \
	done

DSTMP := results/datasets

datasets:
	@mkdir -p $(DSTMP)
	needle simulate configs/datasets/seed000_like.yaml --out $(DSTMP)/seed000_like.h5 --quiet > /dev/null
	needle log from-results $(DSTMP)/seed000_like.h5 --out datasets/seed000_like.h5 --truth-every 5 --prefix s000_
	for p in a b c; do \
	  needle simulate configs/datasets/seed003_like_$$p.yaml --out $(DSTMP)/seed003_like_$$p.h5 --quiet > /dev/null && \
	  needle log from-results $(DSTMP)/seed003_like_$$p.h5 --out $(DSTMP)/seed003_like_$$p.log.h5 --truth-every 10 --prefix s003$$p\_ || exit 1; \
	done
	needle log merge $(DSTMP)/seed003_like_a.log.h5 $(DSTMP)/seed003_like_b.log.h5 $(DSTMP)/seed003_like_c.log.h5 \
	  --out datasets/seed003_like.h5 --description "synthetic, seed 003 manner: media A (4), B (5), two-layer phantom (1)"
	needle simulate configs/datasets/seed004_like.yaml --out $(DSTMP)/seed004_like.h5 --quiet > /dev/null
	needle log from-results $(DSTMP)/seed004_like.h5 --out datasets/seed004_like.h5 --truth-every 2 --prefix s004_

regress:
	@for c in configs/replay/*.yaml; do \
	  n=$$(basename $$c .yaml); \
	  needle simulate $$c --out results/regress/$$n.h5 --quiet > /dev/null && \
	  needle evaluate results/regress/$$n.h5 --out results/regress/$$n --no-plots --quiet --baseline datasets/baselines/$$n.yaml || exit 1; \
	done
