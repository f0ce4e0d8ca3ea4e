# needlecli: common tasks. `make help` lists them.
PY ?= python

STUDIES := results/studies

.PHONY: help install demo test bench lint docs clean datasets regress real real-tau real-plane real-start real-poses shaft owndata faults papers particles
PAPERS := highgain-us2d so3-invariant multirate-ukf-us3d em-magnetic-pratt2022
# the papers' former names (needlecli/papers.py: the seed texts' numbers), kept as aliases of their targets
ALIASES := seed000 seed001 seed003 seed004
.PHONY: $(PAPERS) $(PAPERS:=-numbers) $(ALIASES) $(ALIASES:=-numbers)

help:
	@echo "make install  - install needlecli with test extras (editable)"
	@echo "make demo     - run the bundled default experiment and write its tables"
	@echo "make test     - run the test suite (what .ci/run runs)"
	@echo "make bench    - speed benchmarks (ratios against in-run references; issue 14's targets) -> docs/benchmarks.md"
	@echo "make lint     - ruff"
	@echo "make docs     - the documentation site in site/ (mkdocs build --strict; pip install -e '.[docs]')"
	@echo "make highgain-us2d (formerly seed000) - the high-gain observer paper (2D transverse ultrasound): simulation and experiment-like studies, Table I, the sweep of theta (in $(STUDIES))"
	@echo "make so3-invariant (formerly seed001) - the SO(3) observer paper: helix studies, convergence, half turns, Fig. 3, the alternative reading (in $(STUDIES))"
	@echo "make multirate-ukf-us3d (formerly seed003) - the multi-rate UKF paper (3D ultrasound): Table 1 (and its variant), Figs. 6-8 (results and tables in $(STUDIES))"
	@echo "make em-magnetic-pratt2022 (formerly seed004) - the magnetic needle EM paper (Pratt and Petruska 2022): EM fits, Tables 1-3, Figs. 5, 10 (in $(STUDIES))"
	@echo "make papers   - every number each paper states beside needlecli's over three seeds, into its page (PAPER-numbers: one paper)"
	@echo "make datasets - rebuild the synthetic logs in datasets/ from configs/datasets/"
	@echo "make regress  - replay every bundled data set and check its tables against datasets/baselines/"
	@echo "make faults   - kill simulate, sweep, crossval, compare, log import-csv and fit-em at 20 random points each; check what is on disk"
	@echo "make real     - import the recorded ultrasteer insertions (../shared/real-data) and make their tables in $(REAL)"
	@echo "make real-tau - after make real: the ultrasound's likelihood against the image plane offset's time constant"
	@echo "make real-plane - after make real: the image plane's bound with margins 0-8 mm and lost frames only (tip error against the tracker)"
	@echo "make real-start - after make real: the shaft model's along constant from the ultrasound alone, each candidate reference against the tracker"
	@echo "make real-poses - after make real: the held-out tracker trials predicted from the start and from their own pose at 0-60 mm"
	@echo "make shaft    - the transverse-plane studies: a probe scanning around the tip, shaft-crossing vs tip model; latency (in $(SHAFT))"
	@echo "make owndata  - a lab's exports made by needlecli, imported by a mapping, fitted with and without the slip (in $(OWN))"
	@echo "make particles - the particle filters against the UKF, EKF (Table 1, T2prelim, outliers, resultsOrig) -> docs/guide/particle-filters.md"
	@echo "make clean    - remove results/ and caches"

install:
	$(PY) -m pip install -e '.[test]'

demo:
	needle simulate configs/default.yaml
	needle evaluate results/default.h5

test:
	$(PY) -m pytest

# Every benchmark in order (tools/bench_page.py lists them), their output as it comes, then written down as
# the documentation's benchmark page, docs/benchmarks.md (only when all finished). BENCH_ARGS: arguments of
# benchmarks/bench_kernels.py, e.g. BENCH_ARGS=--quick.
bench:
	$(PY) tools/bench_page.py --out docs/benchmarks.md -- $(BENCH_ARGS)

lint:
	$(PY) -m ruff check needlecli tests benchmarks

# The documentation site: warnings are errors; the reference pages (commands, config keys, tables and plots)
# are generated at build time from the code (tools/docs_hooks.py), the Python API from the docstrings.
docs:
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict

clean:
	rm -rf results site .pytest_cache .ruff_cache .hypothesis

highgain-us2d:
	@for c in simulation experiment_like; do \
	  needle simulate configs/highgain-us2d/$$c.yaml --out $(STUDIES)/highgain-us2d_$$c.h5 --quiet > /dev/null && \
	  needle evaluate $(STUDIES)/highgain-us2d_$$c.h5 --out $(STUDIES)/highgain-us2d || exit 1; \
	done

so3-invariant:
	@for c in helix helix_batch helix_kappa35; do \
	  needle simulate configs/so3-invariant/$$c.yaml --out $(STUDIES)/so3-invariant_$$c.h5 --quiet > /dev/null && \
	  needle evaluate $(STUDIES)/so3-invariant_$$c.h5 --out $(STUDIES)/so3-invariant || exit 1; \
	done

multirate-ukf-us3d:
	@for c in table1 table1_growth_stream fig6 fig7 fig8; do \
	  needle simulate configs/multirate-ukf-us3d/$$c.yaml --out $(STUDIES)/multirate-ukf-us3d_$$c.h5 --quiet > /dev/null && \
	  needle evaluate $(STUDIES)/multirate-ukf-us3d_$$c.h5 --out $(STUDIES)/multirate-ukf-us3d || exit 1; \
	done

em-magnetic-pratt2022:
	@for c in study t2prelim; do \
	  needle fit-em configs/em-magnetic-pratt2022/$$c.yaml --model both --out $(STUDIES)/em-magnetic-pratt2022_$$c.h5 && \
	  needle evaluate $(STUDIES)/em-magnetic-pratt2022_$$c.h5 --out $(STUDIES)/em-magnetic-pratt2022 || exit 1; \
	done

# Every number a paper states beside needlecli's over three seeds (--set runs.seed=S), with a verdict: the
# studies of docs/papers/numbers/PAPER.yaml run once per seed into results/papers/PAPER, the values collected
# into docs/papers/numbers/PAPER_values.yaml, the table written into the paper's page (tools/paper_numbers.py;
# PAPER_ARGS=--reuse keeps results files already there, --render only rewrites the page). Times on the shared
# 2-core machine: docs/papers/numbers/PAPER_values.yaml, made_with.seconds.
$(PAPERS:=-numbers):
	$(PY) tools/paper_numbers.py $(@:-numbers=) $(PAPER_ARGS)

papers: $(PAPERS:=-numbers)

# the former names: seed000 is highgain-us2d, seed000-numbers is highgain-us2d-numbers, ...
seed000: highgain-us2d
seed001: so3-invariant
seed003: multirate-ukf-us3d
seed004: em-magnetic-pratt2022
seed000-numbers: highgain-us2d-numbers
seed001-numbers: so3-invariant-numbers
seed003-numbers: multirate-ukf-us3d-numbers
seed004-numbers: em-magnetic-pratt2022-numbers

DSTMP := results/datasets

datasets:
	@mkdir -p $(DSTMP)
	needle simulate configs/datasets/highgain-us2d_like.yaml --out $(DSTMP)/highgain-us2d_like.h5 --quiet > /dev/null
	needle log from-results $(DSTMP)/highgain-us2d_like.h5 --out datasets/highgain-us2d_like.h5 --truth-every 5 --prefix s000_
	for p in a b c; do \
	  needle simulate configs/datasets/multirate-ukf-us3d_like_$$p.yaml --out $(DSTMP)/multirate-ukf-us3d_like_$$p.h5 --quiet > /dev/null && \
	  needle log from-results $(DSTMP)/multirate-ukf-us3d_like_$$p.h5 --out $(DSTMP)/multirate-ukf-us3d_like_$$p.log.h5 --truth-every 10 --prefix s003$$p\_ || exit 1; \
	done
	needle log merge $(DSTMP)/multirate-ukf-us3d_like_a.log.h5 $(DSTMP)/multirate-ukf-us3d_like_b.log.h5 $(DSTMP)/multirate-ukf-us3d_like_c.log.h5 \
	  --out datasets/multirate-ukf-us3d_like.h5 --description "synthetic, multirate-ukf-us3d manner: media A (4), B (5), two-layer phantom (1)"
	needle simulate configs/datasets/em-magnetic-pratt2022_like.yaml --out $(DSTMP)/em-magnetic-pratt2022_like.h5 --quiet > /dev/null
	needle log from-results $(DSTMP)/em-magnetic-pratt2022_like.h5 --out datasets/em-magnetic-pratt2022_like.h5 --truth-every 2 --prefix s004_

regress:
	@for c in configs/replay/*.yaml; do \
	  n=$$(basename $$c .yaml); \
	  needle simulate $$c --out results/regress/$$n.h5 --quiet > /dev/null && \
	  needle evaluate results/regress/$$n.h5 --out results/regress/$$n --no-plots --quiet --baseline datasets/baselines/$$n.yaml || exit 1; \
	done

# Fault injection (issue 16): SIGKILL, SIGTERM, SIGINT at random points of simulate and sweep (local
# processes), what is on disk checked after each, sweep --resume to the same table (a few minutes).
faults:
	$(PY) tools/faults.py --points 20 --executor local --work results/faults

# Recorded insertions (issue 8): the data stay outside the repository; not part of CI (about 4 minutes
# on 2 cores, most of it EM). NEEDLECLI_REAL_DATA overrides where they are.
# The transverse-plane studies (docs/guide/observers.md, "Transverse planes"): the
# scanning probe read as the shaft's crossing and as the tip (configs/shaft/scan.yaml); a tip sensor's late
# samples used at their arrival or their acquisition (configs/shaft/latency.yaml). Tables in $(SHAFT).
SHAFT := results/shaft

shaft:
	@mkdir -p $(SHAFT)
	needle simulate configs/shaft/scan.yaml --out $(SHAFT)/scan.h5 --quiet > /dev/null
	needle evaluate $(SHAFT)/scan.h5 --out $(SHAFT)/scan --tables summary,consistency --no-plots --quiet
	@# delayed samples used at their arrival or their acquisition (configs/shaft/latency.yaml), latency in s
	@for L in 0 0.04 0.1 0.3; do \
	  needle simulate configs/shaft/latency.yaml --set sensors.0.latency=$$L --out $(SHAFT)/latency_$$L.h5 --quiet \
	    > /dev/null && \
	  needle evaluate $(SHAFT)/latency_$$L.h5 --out $(SHAFT)/latency_$$L --tables summary,consistency --no-plots \
	    --quiet || exit 1; \
	done
	@echo "tables: $(SHAFT)/scan, $(SHAFT)/latency_*"

REAL := results/real
REAL_DATA ?= $(or $(NEEDLECLI_REAL_DATA),../shared/real-data/ultrasteer)

real:
	@mkdir -p $(REAL)
	needle import ultrasteer $(REAL_DATA) --out $(REAL)/ultrasteer.h5
	@for c in ukf_resultsorig so3_9_18_15 so3_1_7_16; do \
	  needle simulate configs/real/$$c.yaml --out $(REAL)/$$c.h5 --quiet > /dev/null && \
	  needle evaluate $(REAL)/$$c.h5 --out $(REAL)/tables --no-plots --quiet || exit 1; \
	done
	@if needle fit-em --help > /dev/null 2>&1; then \
	  needle fit-em configs/real/em_tracker.yaml --out $(REAL)/em_tracker.h5 --quiet && \
	  needle evaluate $(REAL)/em_tracker.h5 --out $(REAL)/tables --tables fit_status,em_per_trial,em_per_speed,em_loglik \
	    --no-plots --quiet || exit 1; \
	else \
	  echo "needle fit-em is not available: table (c), EM on the 18 tracker trials, is skipped"; \
	fi
	@# (a2) the UKF tuned by EM: the needle from the day's other tracker trials, the ultrasound from its own data
	needle fit-em configs/real/em_tracker_9_18_15_others.yaml --out $(REAL)/em_tracker_9_18_15_others.h5 --quiet
	needle fit-em configs/real/em_resultsorig.yaml --out $(REAL)/em_resultsorig.h5 --quiet
	needle evaluate $(REAL)/em_resultsorig.h5 --out $(REAL)/tables --tables identifiability,em_per_trial --no-plots --quiet
	needle simulate configs/real/ukf_resultsorig_em.yaml --out $(REAL)/ukf_resultsorig_em.h5 --quiet > /dev/null
	needle evaluate $(REAL)/ukf_resultsorig_em.h5 --out $(REAL)/tables --quiet
	@# (a3) the ultrasound read as a plane that sees the shaft, with the inserted length: EM for the sensors'
	@# noise (the needle's motion held by its physics), the causal UKF, the fixed-lag smoother, side by side
	needle fit-em configs/real/em_resultsorig_shaft.yaml --out $(REAL)/em_resultsorig_shaft.h5 --quiet
	needle fit-em configs/real/em_resultsorig_shaft_start.yaml --out $(REAL)/em_resultsorig_shaft_start.h5 --quiet
	needle fit-em configs/real/em_resultsorig_shaft_edge.yaml --out $(REAL)/em_resultsorig_shaft_edge.h5 --quiet
	needle simulate configs/real/ukf_resultsorig_shaft.yaml --out $(REAL)/ukf_resultsorig_shaft.h5 --quiet > /dev/null
	needle evaluate $(REAL)/ukf_resultsorig_shaft.h5 --out $(REAL)/tables --tables real_tip_error,real_error_along_across \
	  --no-plots --quiet
	@# (a4) the shaft model's along constant from the ultrasound alone: every candidate reference against the tracker
	$(PY) tools/along_start.py --runs 20 > /dev/null
	@# (d) the tracker trials cross-validated: EM on the other trials of the day, the held-out path from its first pose
	needle crossval configs/real/em_tracker.yaml --observer open_loop --leave-one-out --group-by 'id~^[^-]+' --within \
	  --out $(REAL)/crossval --quiet > /dev/null
	@# (d) again, EM on the other trials of the day at the held-out one's speed only
	needle crossval configs/real/em_tracker.yaml --observer open_loop --leave-one-out --group-by 'id~^[^-]+-[^-]+' --within \
	  --out $(REAL)/crossval_speed --quiet > /dev/null
	@echo "tables: $(REAL)/tables, $(REAL)/along_start, $(REAL)/crossval, $(REAL)/crossval_speed"

# The time constant of the image plane's offset (configs/real/em_resultsorig.yaml): the ultrasound's
# log-likelihood at EM's fit for each tau (needs `make real` first); tables in $(REAL)/tau.
TAUS := 0.5 1.0 2.0 4.0 8.0 16.0
real-tau:
	@mkdir -p $(REAL)/tau
	@for t in $(TAUS); do \
	  needle fit-em configs/real/em_resultsorig.yaml --out $(REAL)/tau/em_resultsorig_tau$$t.h5 --quiet \
	    --set fit.measurements.us.along_offset.tau=$$t --set fit.identify.enabled=false > /dev/null && \
	  needle evaluate $(REAL)/tau/em_resultsorig_tau$$t.h5 --out $(REAL)/tau/$$t --tables em_per_trial --no-plots --quiet || exit 1; \
	  echo "tau $$t s: $$(grep resultsOrig $(REAL)/tau/$$t/*em_per_trial.md)"; \
	done

# The image plane as a one-sided bound (configs/real/ukf_resultsorig_em.yaml, observers ukf_em_plane and
# ukf_em_white_plane_m5): the margin a seen needle's tip may lie short of the plane, swept (needs `make real`
# first); the along/across tables in $(REAL)/plane/<margin>.
MARGINS := 0.0 1.0 2.0 3.0 4.0 5.0 6.0 8.0
real-plane:
	@mkdir -p $(REAL)/plane
	@for m in $(MARGINS); do \
	  needle simulate configs/real/ukf_resultsorig_em.yaml --out $(REAL)/plane/margin$$m.h5 --quiet \
	    --set observers.4.measurements.plane.margin=$$m --set observers.5.measurements.plane.margin=$$m > /dev/null && \
	  needle evaluate $(REAL)/plane/margin$$m.h5 --out $(REAL)/plane/$$m --tables real_error_along_across --no-plots --quiet || exit 1; \
	  echo "margin $$m mm:"; grep -E '^\| (ukf_em_plane|ukf_em_white_plane_m5) ' $(REAL)/plane/$$m/*along_across.md | cut -d'|' -f2-7; \
	done
	@# the lost frames only (sides: [short]), no margin
	@needle simulate configs/real/ukf_resultsorig_em.yaml --out $(REAL)/plane/short.h5 --quiet \
	  --set 'observers.4.measurements.plane.sides=[short]' --set 'observers.5.measurements.plane.sides=[short]' \
	  --set observers.5.measurements.plane.margin=0.0 > /dev/null
	@needle evaluate $(REAL)/plane/short.h5 --out $(REAL)/plane/short --tables real_error_along_across --no-plots --quiet
	@echo "lost frames only:"; grep -E '^\| (ukf_em_plane|ukf_em_white_plane_m5) ' $(REAL)/plane/short/*along_across.md | cut -d'|' -f2-7

# The along constant of the shaft model without the tracker (docs/real-data.md (a4)): the detector's seen/lost
# boundary against the tracked tip, the length's reference from the ultrasound alone (first seen frame, first
# sweep, the verdicts' boundary, the scan's mean), each run through ukf_shaft_em of
# configs/real/ukf_resultsorig_shaft.yaml, and EM's log-likelihood against the reference (a step of `make real`;
# alone after it, about 2 minutes). Table in $(REAL)/along_start/along_start.md.
real-start:
	$(PY) tools/along_start.py --runs 20

# The two parts of the held-out error on the tracker trials (docs/real-data.md (d), issue 30): leave one out
# within the day as make real's crossval, each held-out trial also predicted from its own pose at 0-60 mm,
# the recorded one and the one a smoother tuned by the fold's EM gives (configs/real/em_tracker_poses.yaml;
# needs make real's log; about as long as make real's crossval, most of it EM). Tables in $(REAL)/crossval_poses.
real-poses:
	needle crossval configs/real/em_tracker_poses.yaml --observer open_loop --observer eks --leave-one-out \
	  --group-by 'id~^[^-]+' --within --from-depths 0,10,20,30,40,60 --pose-from truth --pose-from eks_em \
	  --out $(REAL)/crossval_poses --quiet > /dev/null
	@echo "tables: $(REAL)/crossval_poses (crossval_from_pose: the start's part and the model's)"

# Bringing your own recorded data (issue 18, docs/tutorials/own-data.md): a synthetic study in
# the shape of a lab's exports (step-indexed tracker poses with quaternions, zero rows, per-sample rms, a
# command file per trial; kappa = 0.012 (1 - duty_cycle), 86-94 % slip), imported by the mapping the export
# writes, fitted by EM with the speed scale and without it; tables and plots in $(OWN)/tables. OWN_RUNS
# trials (the 12 combinations of duty cycle and slip, repeated; the test suite runs 12).
OWN := results/owndata
OWN_RUNS ?= 48

owndata:
	@mkdir -p $(OWN)
	needle simulate configs/owndata/study.yaml --runs $(OWN_RUNS) --out $(OWN)/study.h5 --quiet > /dev/null
	needle log from-results $(OWN)/study.h5 --out $(OWN)/study_log.h5
	needle log export-csv $(OWN)/study_log.h5 --out $(OWN)/exports --tracker-pose 10,80,25,120,-40,15 --sensor-roll 35
	needle log import-csv $(OWN)/exports/mapping.yaml --out $(OWN)/lab.h5
	needle log info $(OWN)/lab.h5 > $(OWN)/lab_info.txt
	needle fit-em configs/owndata/fit.yaml --out $(OWN)/fit.h5 --quiet
	needle fit-em configs/owndata/fit_no_scale.yaml --out $(OWN)/fit_no_scale.h5 --quiet
	needle evaluate $(OWN)/fit.h5 --out $(OWN)/tables --quiet
	needle evaluate $(OWN)/fit_no_scale.h5 --out $(OWN)/tables --quiet
	@echo "tables: $(OWN)/tables; what the import read and dropped: $(OWN)/lab_info.txt"

# The particle filters (issue 29, docs/guide/particle-filters.md): needle compare of each config in
# configs/particles/ (the multi-rate UKF paper's Table 1 with 100 to 1000 particles, the magnetic needle
# EM paper's T2prelim with the bicycle model, Table 1 with gross ultrasound errors, the recorded
# resultsOrig after `make real`), their tables written on the page. The first 20 runs of each study (a shared 2-core machine takes about 40 minutes;
# the minute figure is scaled to Table 1's 100 insertions). PARTICLES_ARGS: e.g. --runs 100 (the configs'
# counts), --only table1, --render.
PARTICLES_ARGS ?= --runs 20
particles:
	$(PY) tools/particles_page.py $(PARTICLES_ARGS)
