// A small interpreter for a recorded list of ATen operator calls.
//
// ``learners/traced.py`` records one training step of a learner (its own ``update``:
// forwards, autograd's backward, the optimiser) as the exact sequence of operator calls
// it made, and hands that sequence here. ``run`` replays it through the dispatcher's
// boxed calling convention: the same operators with the same arguments, so the same
// bytes as the recorded Python, without Python, autograd or the optimiser's per-call
// overhead. Nothing in this file knows about any learner.
//
// With more than one worker (``set_workers``), calls whose inputs are ready run on
// several cores at once: the two critics' backward passes beside each other, the
// policy's forward beside the critics' fit. ``traced.py`` hands over, per call, the
// earlier calls it must wait for (its data, and the tensors it overwrites or that
// others overwrite after it reads them, views included, and the random generator), so
// every call sees exactly the tensors it saw in the recording: the bytes are the same
// with any number of workers. Among ready calls, the one with the longest measured
// chain of work still behind it goes first.
#include <torch/extension.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <ATen/Parallel.h>
#include <ATen/ScalarOps.h>
#include <ATen/ThreadLocalState.h>
#include <c10/core/InferenceMode.h>
#include <torch/csrc/Generator.h>
#include <torch/csrc/jit/python/pybind_utils.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <exception>
#include <mutex>
#include <queue>
#include <string>
#include <thread>
#include <unordered_map>
#include <unordered_set>
#include <unistd.h>
#include <vector>

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>  // _mm_pause
#endif

namespace {

namespace py = pybind11;
using c10::IValue;

// One argument of one call: a constant, a value slot, or a list of slots.
struct Arg {
  enum Kind { kConstant, kSlot, kTensorList, kOptionalTensorList } kind;
  IValue constant;
  int slot = -1;
  std::vector<int> slots;  // kTensorList / kOptionalTensorList (-1: None)
};

struct Call {
  std::optional<c10::OperatorHandle> op;  // none: a list-element read
  std::vector<Arg> args;
  std::vector<int> outputs;  // one slot per schema return
  int list_source = -1;      // a list-element read: slots[list_source][list_index]
  int64_t list_index = 0;
  std::vector<int> release;  // slots whose last use is this call
};

inline void cpu_relax() {
#if defined(__x86_64__) || defined(__i386__)
  _mm_pause();
#else
  std::this_thread::yield();
#endif
}

// Waiting on another worker: spin briefly (a call takes microseconds), then give the
// core away at each turn, so that on a busy machine the worker waited for can run.
struct Backoff {
  int spins = 0;
  void wait() {
    if (++spins < 4000) cpu_relax();
    else std::this_thread::yield();
  }
  void reset() { spins = 0; }
};

class Program {
 public:
  explicit Program(int64_t n_slots) : slots_(n_slots) {}

  ~Program() { stop_helpers(); }

  void set_constant(int slot, const IValue& value) {
    slots_.at(slot) = value;
  }

  void set_inputs(std::vector<int> inputs) { inputs_ = std::move(inputs); }
  void set_outputs(std::vector<int> outputs) { outputs_ = std::move(outputs); }

  // specs: one tuple per schema argument: ("const", value) | ("slot", i) | ("slots", [i, ...])
  void add_call(const std::string& name, const std::string& overload, const py::list& specs,
                std::vector<int> outputs, std::vector<int> release) {
    Call call;
    call.op = c10::Dispatcher::singleton().findSchemaOrThrow(name.c_str(), overload.c_str());
    const auto& schema = call.op->schema();
    TORCH_CHECK(specs.size() == schema.arguments().size(), name, ".", overload, ": ", specs.size(),
                " arguments for a schema of ", schema.arguments().size());
    for (size_t i = 0; i < specs.size(); ++i) {
      auto spec = specs[i].cast<py::tuple>();
      auto kind = spec[0].cast<std::string>();
      Arg arg;
      if (kind == "const") {
        arg.kind = Arg::kConstant;
        arg.constant = torch::jit::toIValue(spec[1], schema.arguments()[i].type());
      } else if (kind == "wrapped") {
        // a Python number where the schema takes a Tensor: wrapped as Python's binding
        // does, so type promotion treats it as a scalar
        arg.kind = Arg::kConstant;
        at::Tensor t = c10::scalar_to_tensor(torch::jit::toIValue(spec[1], c10::NumberType::get()).toScalar());
        t.unsafeGetTensorImpl()->set_wrapped_number(true);
        arg.constant = IValue(t);
      } else if (kind == "slot") {
        arg.kind = Arg::kSlot;
        arg.slot = spec[1].cast<int>();
      } else {
        auto elem = schema.arguments()[i].type()->containedTypes();
        bool optional = !elem.empty() && elem[0]->kind() == c10::TypeKind::OptionalType;
        arg.kind = optional ? Arg::kOptionalTensorList : Arg::kTensorList;
        arg.slots = spec[1].cast<std::vector<int>>();
      }
      call.args.push_back(std::move(arg));
    }
    call.outputs = std::move(outputs);
    call.release = std::move(release);
    calls_.push_back(std::move(call));
  }

  // a read of element ``index`` of the list (or tuple) in slot ``source``
  void add_list_element(int source, int64_t index, int output, std::vector<int> release) {
    Call call;
    call.list_source = source;
    call.list_index = index;
    call.outputs = {output};
    call.release = std::move(release);
    calls_.push_back(std::move(call));
  }

  // For running on several workers: the earlier calls each call waits for, and the
  // slots never released (inputs, constants, outputs).
  void set_dependencies(const std::vector<std::vector<int>>& waits_for, const std::vector<int>& keep,
                        const std::vector<int>& groups) {
    TORCH_CHECK(groups.size() == slots_.size(), groups.size(), " groups for ", slots_.size(), " slots");
    groups_ = groups;
    TORCH_CHECK(waits_for.size() == calls_.size(), waits_for.size(), " dependency lists for ", calls_.size(), " calls");
    const size_t n = calls_.size();
    successors_.assign(n, {});
    n_waits_.assign(n, 0);
    for (size_t i = 0; i < n; ++i) {
      for (int j : waits_for[i]) {
        TORCH_CHECK(j >= 0 && static_cast<size_t>(j) < i, "call ", i, " waits for call ", j, ", which is not earlier");
        successors_[j].push_back(static_cast<int>(i));
        ++n_waits_[i];
      }
    }
    keep_.assign(slots_.size(), false);
    for (int s : keep) keep_.at(s) = true;
    // each call's distinct slots read; a slot is released when its last reader is done
    reads_.assign(n, {});
    n_readers_.assign(slots_.size(), 0);
    for (size_t i = 0; i < n; ++i) {
      std::vector<int> r;
      const Call& call = calls_[i];
      if (call.list_source >= 0) r.push_back(call.list_source);
      for (const auto& arg : call.args) {
        if (arg.kind == Arg::kSlot) r.push_back(arg.slot);
        for (int s : arg.slots)
          if (s >= 0) r.push_back(s);
      }
      std::sort(r.begin(), r.end());
      r.erase(std::unique(r.begin(), r.end()), r.end());
      for (int s : r) ++n_readers_[s];
      reads_[i] = std::move(r);
    }
    // the groups each call writes (arguments its schema marks as written)
    written_groups_.clear();
    for (const Call& call : calls_) {
      if (!call.op) continue;
      const auto& args = call.op->schema().arguments();
      for (size_t a = 0; a < call.args.size(); ++a) {
        const auto* alias = args[a].alias_info();
        if (!alias || !alias->isWrite()) continue;
        if (call.args[a].kind == Arg::kSlot) written_groups_.insert(groups_[call.args[a].slot]);
        for (int sl : call.args[a].slots)
          if (sl >= 0) written_groups_.insert(groups_[sl]);
      }
    }
    cost_us_.assign(n, 1.0);
    rank_.assign(n, 0.0);
    parallel_ok_ = true;
    not_parallel_why_.clear();
    measured_ = false;
    runs_in_order_ = 0;
    has_dependencies_ = true;
  }

  // Worker threads (this one included) a run may use; 1 runs the calls in order.
  // ``choose``: use at most ``workers``, as many as the timed run says pay: a step of W
  // microseconds of calls whose longest chain is C cannot take less than max(W / n, C),
  // so more than ceil(W / C) threads only wait.
  // May be called between runs at any time (a run's result does not depend on it).
  void set_workers(int workers, bool choose) {
    TORCH_CHECK(workers >= 1, "workers must be >= 1, got ", workers);
    stop_helpers();
    workers_ = max_workers_ = workers;
    choose_workers_ = choose;
    if (measured_) choose_from_measurements();
  }

  int workers() const { return workers_; }

  // True once the calls are timed (the in-order runs before that are done)
  bool measured() const { return measured_; }

  // Threads the runs use now: 1 until the calls are timed, or if values share memory
  // their operators do not declare (``why_in_order`` says which).
  int threads_in_use() const { return (workers_ > 1 && has_dependencies_ && measured_ && parallel_ok_) ? workers_ : 1; }
  std::string why_in_order() const { return not_parallel_why_; }

  // (sum of the calls' measured microseconds, longest chain of them): the step's time
  // on one worker and its bound on many
  std::pair<double, double> measured_us() const {
    double total = 0.0, chain = 0.0;
    for (double c : cost_us_) total += c;
    for (double r : rank_) chain = std::max(chain, r);
    return {total, chain};
  }

  std::vector<at::Tensor> run(const std::vector<at::Tensor>& inputs) {
    TORCH_CHECK(inputs.size() == inputs_.size(), "expected ", inputs_.size(), " inputs, got ", inputs.size());
    c10::InferenceMode guard;
    for (size_t i = 0; i < inputs.size(); ++i) slots_[inputs_[i]] = inputs[i];
    if (threads_in_use() > 1) {
      run_parallel();
    } else if (!has_dependencies_ || measured_) {
      run_in_order(Pass::kPlain);
    } else {
      // before the calls run on several workers: the first run pays for first-use
      // set-up; the second checks how values share memory (keeping every value, so
      // that no memory is reused within it); the next ones time each call, releasing
      // values as usual so the timing sees memory as later runs do
      const int pass = runs_in_order_ + 1;  // counted once it has run: a failed check is not skipped
      run_in_order(pass == 1 ? Pass::kPlain : pass == 2 ? Pass::kCheckSharing : Pass::kTime);
      runs_in_order_ = pass;
      if (runs_in_order_ == 2 + kTimedRuns) finish_measuring();
    }
    std::vector<at::Tensor> out;
    out.reserve(outputs_.size());
    for (int s : outputs_) out.push_back(slots_[s].toTensor());
    for (int s : inputs_) slots_[s] = IValue();
    return out;
  }

  // (operator, measured microseconds: the median of the timed runs) per call, in recorded order
  std::vector<std::pair<std::string, double>> call_times_us() const {
    std::vector<std::pair<std::string, double>> out;
    for (size_t i = 0; i < calls_.size(); ++i) {
      const Call& c = calls_[i];
      std::string name = c.op ? c.op->schema().name() + "." + c.op->schema().overload_name() : "list_element";
      out.emplace_back(std::move(name), i < cost_us_.size() ? cost_us_[i] : 0.0);
    }
    return out;
  }

 private:
  void execute(Call& call, torch::jit::Stack& stack) {
    if (call.list_source >= 0) {
      const IValue& src = slots_[call.list_source];
      slots_[call.outputs[0]] =
          src.isTuple() ? src.toTupleRef().elements()[call.list_index] : src.toListRef()[call.list_index];
      return;
    }
    stack.clear();
    for (const auto& arg : call.args) {
      switch (arg.kind) {
        case Arg::kConstant:
          stack.push_back(arg.constant);
          break;
        case Arg::kSlot:
          stack.push_back(slots_[arg.slot]);
          break;
        case Arg::kTensorList: {
          c10::List<at::Tensor> list;
          list.reserve(arg.slots.size());
          for (int s : arg.slots) list.push_back(slots_[s].toTensor());
          stack.emplace_back(std::move(list));
          break;
        }
        case Arg::kOptionalTensorList: {
          c10::List<std::optional<at::Tensor>> list;
          list.reserve(arg.slots.size());
          for (int s : arg.slots) {
            list.push_back(s < 0 ? std::optional<at::Tensor>() : std::optional<at::Tensor>(slots_[s].toTensor()));
          }
          stack.emplace_back(std::move(list));
          break;
        }
      }
    }
    call.op->callBoxed(&stack);
    for (size_t r = 0; r < call.outputs.size(); ++r) slots_[call.outputs[r]] = std::move(stack[r]);
  }

  enum class Pass { kPlain, kCheckSharing, kTime };

  // In recorded order. ``kCheckSharing`` keeps every value to the end of the run and
  // checks that values share memory only as the groups say; ``kTime`` times each call.
  void run_in_order(Pass pass) {
    torch::jit::Stack stack;
    if (pass == Pass::kTime && timed_us_.size() != calls_.size()) timed_us_.assign(calls_.size(), {});
    for (size_t i = 0; i < calls_.size(); ++i) {
      if (pass == Pass::kTime) {
        auto t0 = std::chrono::steady_clock::now();
        execute(calls_[i], stack);
        timed_us_[i].push_back(std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count());
      } else {
        execute(calls_[i], stack);
      }
      if (pass != Pass::kCheckSharing)
        for (int s : calls_[i].release) slots_[s] = IValue();
    }
    if (pass == Pass::kCheckSharing) {
      check_memory_sharing();
      for (size_t i = 0; i < calls_.size(); ++i)
        for (int s : calls_[i].release) slots_[s] = IValue();
    }
  }

  // Each call's cost: the median of its timed runs. A call's rank: its own cost and the
  // longest chain of calls waiting on it.
  void finish_measuring() {
    for (size_t i = 0; i < calls_.size(); ++i) {
      auto& t = timed_us_[i];
      std::nth_element(t.begin(), t.begin() + t.size() / 2, t.end());
      cost_us_[i] = t[t.size() / 2];
    }
    timed_us_.clear();
    for (size_t k = calls_.size(); k-- > 0;) {
      double longest = 0.0;
      for (int j : successors_[k]) longest = std::max(longest, rank_[j]);
      rank_[k] = cost_us_[k] + longest;
    }
    choose_from_measurements();
    measured_ = true;
  }

  void choose_from_measurements() {
    if (!choose_workers_) return;
    auto [work, chain] = measured_us();
    int useful = chain > 0.0 ? static_cast<int>(std::ceil(work / chain)) : 1;
    workers_ = std::max(1, std::min(max_workers_, useful));
  }

  // A storage used by values of two groups, one of them written by some call: a call
  // could then overwrite memory another reads without waiting for it. Run in order.
  void check_memory_sharing() {
    std::unordered_map<const c10::StorageImpl*, std::pair<int, int>> seen;  // storage -> (group, slot)
    auto visit = [&](const at::Tensor& t, int slot) {
      if (!t.defined() || !t.has_storage()) return;
      const c10::StorageImpl* impl = t.storage().unsafeGetStorageImpl();
      auto [it, fresh] = seen.emplace(impl, std::make_pair(groups_[slot], slot));
      int g = it->second.first;
      if (fresh || g == groups_[slot]) return;
      if (written_groups_.count(g) || written_groups_.count(groups_[slot])) {
        if (parallel_ok_)
          not_parallel_why_ = "values " + std::to_string(it->second.second) + " and " + std::to_string(slot) +
                              " share memory that their operators do not declare";
        parallel_ok_ = false;
      }
    };
    for (size_t s = 0; s < slots_.size(); ++s) {
      const IValue& v = slots_[s];
      if (v.isTensor()) {
        visit(v.toTensor(), static_cast<int>(s));
      } else if (v.isTensorList()) {
        for (const at::Tensor& t : v.toTensorVector()) visit(t, static_cast<int>(s));
      } else if (v.isTuple()) {
        for (const IValue& e : v.toTupleRef().elements())
          if (e.isTensor()) visit(e.toTensor(), static_cast<int>(s));
      } else if (v.isList()) {
        for (const IValue& e : v.toListRef())
          if (e.isTensor()) visit(e.toTensor(), static_cast<int>(s));
      }
    }
  }

  // ---- several workers --------------------------------------------------------------
  struct ByRank {
    const std::vector<double>* rank;
    bool operator()(int a, int b) const {  // the priority queue's "less": lower rank, or later call
      return (*rank)[a] < (*rank)[b] || ((*rank)[a] == (*rank)[b] && a > b);
    }
  };

  bool outranks(int a, int b) const { return ByRank{&rank_}(b, a); }

  void push_ready(int i) {
    std::lock_guard<std::mutex> lock(ready_mutex_);
    ready_.push(i);
    n_ready_.fetch_add(1, std::memory_order_release);
  }

  int pop_ready() {
    if (n_ready_.load(std::memory_order_acquire) == 0) return -1;  // idle workers poll without the lock
    std::lock_guard<std::mutex> lock(ready_mutex_);
    if (ready_.empty()) return -1;
    int i = ready_.top();
    ready_.pop();
    n_ready_.fetch_sub(1, std::memory_order_release);
    return i;
  }

  // ``mine`` (just made ready here), or a queued call that outranks it
  int keep_or_swap(int mine) {
    if (n_ready_.load(std::memory_order_acquire) == 0) return mine;
    std::lock_guard<std::mutex> lock(ready_mutex_);
    if (ready_.empty() || !outranks(ready_.top(), mine)) return mine;
    int top = ready_.top();
    ready_.pop();
    ready_.push(mine);
    return top;
  }

  // Take ready calls until every call of this run is done (or one failed).
  void work() {
    torch::jit::Stack stack;
    const int n = static_cast<int>(calls_.size());
    Backoff backoff;
    int next = -1;
    while (done_.load(std::memory_order_acquire) < n && !failed_.load(std::memory_order_relaxed)) {
      int i = next >= 0 ? next : pop_ready();
      next = -1;
      if (i < 0) {
        backoff.wait();
        continue;
      }
      backoff.reset();
      try {
        execute(calls_[i], stack);
      } catch (...) {
        std::lock_guard<std::mutex> lock(error_mutex_);
        if (!error_) error_ = std::current_exception();
        failed_.store(true);
        return;
      }
      for (int s : reads_[i])
        if (readers_left_[s].fetch_sub(1, std::memory_order_acq_rel) == 1 && !keep_[s]) slots_[s] = IValue();
      for (int s : calls_[i].outputs)
        if (n_readers_[s] == 0 && !keep_[s]) slots_[s] = IValue();
      // Of the calls this one made ready, this thread goes on with the best, whose
      // inputs are in this core's cache (unless a queued call outranks it); the rest
      // are queued for any worker.
      for (int j : successors_[i]) {
        if (waits_left_[j].fetch_sub(1, std::memory_order_acq_rel) != 1) continue;
        if (next < 0) {
          next = j;
        } else if (outranks(j, next)) {
          push_ready(next);
          next = j;
        } else {
          push_ready(j);
        }
      }
      done_.fetch_add(1, std::memory_order_acq_rel);
      if (next >= 0) next = keep_or_swap(next);
    }
  }

  void run_parallel() {
    const size_t n = calls_.size();
    if (waits_left_.size() != n) waits_left_ = std::vector<std::atomic<int>>(n);
    if (readers_left_.size() != slots_.size()) readers_left_ = std::vector<std::atomic<int>>(slots_.size());
    for (size_t i = 0; i < n; ++i) waits_left_[i].store(n_waits_[i], std::memory_order_relaxed);
    for (size_t s = 0; s < slots_.size(); ++s) readers_left_[s].store(n_readers_[s], std::memory_order_relaxed);
    ready_ = std::priority_queue<int, std::vector<int>, ByRank>(ByRank{&rank_});
    for (size_t i = 0; i < n; ++i)
      if (n_waits_[i] == 0) ready_.push(static_cast<int>(i));
    n_ready_.store(static_cast<int>(ready_.size()), std::memory_order_release);
    done_.store(0);
    failed_.store(false);
    error_ = nullptr;
    start_helpers();
    state_ = at::ThreadLocalState();
    gate_.store(0, std::memory_order_release);  // helpers may join this run from now
    {
      std::lock_guard<std::mutex> lock(wake_mutex_);
      generation_.fetch_add(1, std::memory_order_acq_rel);
    }
    wake_.notify_all();
    work();
    // A helper that has not joined by now is not waited for (on a busy machine it may
    // not get a core for a while); one that has is inside ``work`` and about to leave.
    gate_.fetch_or(kGateClosed, std::memory_order_acq_rel);
    Backoff backoff;
    while ((gate_.load(std::memory_order_acquire) & ~kGateClosed) != 0) backoff.wait();
    if (error_) {
      for (size_t s = 0; s < slots_.size(); ++s)
        if (!keep_[s]) slots_[s] = IValue();
      std::rethrow_exception(error_);
    }
  }

  bool join_run() {
    int v = gate_.load(std::memory_order_acquire);
    while (!(v & kGateClosed)) {
      if (gate_.compare_exchange_weak(v, v + 1, std::memory_order_acq_rel)) return true;
    }
    return false;
  }

  void start_helpers() {
    if (!helpers_.empty() && helpers_pid_ == getpid()) return;
    for (auto& t : helpers_) t.detach();  // after a fork the threads are gone: start new ones
    helpers_.clear();
    helpers_pid_ = getpid();
    stopping_.store(false);
    for (int w = 1; w < workers_; ++w) helpers_.emplace_back([this] { helper_loop(); });
  }

  void stop_helpers() {
    if (helpers_.empty()) return;
    if (helpers_pid_ == getpid()) {
      {
        std::lock_guard<std::mutex> lock(wake_mutex_);
        stopping_.store(true);
      }
      wake_.notify_all();
      for (auto& t : helpers_) t.join();
    } else {
      for (auto& t : helpers_) t.detach();  // another process's threads
    }
    helpers_.clear();
  }

  void helper_loop() {
    at::init_num_threads();
    uint64_t seen = generation_.load(std::memory_order_acquire);
    while (true) {
      // spin a little before sleeping: the next step usually follows within microseconds
      auto until = std::chrono::steady_clock::now() + std::chrono::microseconds(kSpinUs);
      while (generation_.load(std::memory_order_acquire) == seen && !stopping_.load(std::memory_order_relaxed) &&
             std::chrono::steady_clock::now() < until)
        cpu_relax();
      if (generation_.load(std::memory_order_acquire) == seen) {
        std::unique_lock<std::mutex> lock(wake_mutex_);
        wake_.wait(lock, [&] { return stopping_.load() || generation_.load() != seen; });
      }
      if (stopping_.load()) return;
      seen = generation_.load(std::memory_order_acquire);
      if (!join_run()) continue;
      {
        at::ThreadLocalStateGuard tls(state_);
        c10::InferenceMode guard;
        work();
      }
      gate_.fetch_sub(1, std::memory_order_acq_rel);
    }
  }

  static constexpr int kGateClosed = 1 << 30;
  static constexpr int kSpinUs = 300;

  std::vector<IValue> slots_;
  std::vector<Call> calls_;
  std::vector<int> inputs_, outputs_;

  // dependencies (set_dependencies)
  bool has_dependencies_ = false;
  std::vector<int> groups_;
  std::unordered_set<int> written_groups_;
  bool parallel_ok_ = true;
  std::string not_parallel_why_;
  bool measured_ = false;
  int runs_in_order_ = 0;
  static constexpr int kTimedRuns = 5;  // in-order runs timed call by call
  std::vector<std::vector<double>> timed_us_;
  std::vector<std::vector<int>> successors_;
  std::vector<int> n_waits_;
  std::vector<std::vector<int>> reads_;
  std::vector<int> n_readers_;
  std::vector<bool> keep_;
  std::vector<double> cost_us_, rank_;

  // one parallel run's state
  int workers_ = 1, max_workers_ = 1;
  bool choose_workers_ = false;
  std::vector<std::atomic<int>> waits_left_, readers_left_;
  std::mutex ready_mutex_;
  std::priority_queue<int, std::vector<int>, ByRank> ready_{ByRank{nullptr}};
  std::atomic<int> n_ready_{0};  // calls in ready_
  std::atomic<int> done_{0};
  std::atomic<bool> failed_{false};
  std::mutex error_mutex_;
  std::exception_ptr error_;
  at::ThreadLocalState state_;

  // helper threads
  std::vector<std::thread> helpers_;
  pid_t helpers_pid_ = 0;
  std::mutex wake_mutex_;
  std::condition_variable wake_;
  std::atomic<uint64_t> generation_{0};
  std::atomic<bool> stopping_{false};
  std::atomic<int> gate_{kGateClosed};
};

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  py::class_<Program>(m, "Program")
      .def(py::init<int64_t>())
      .def("set_constant",
           [](Program& p, int slot, const at::Tensor& t) { p.set_constant(slot, IValue(t)); })
      .def("set_constant",  // a torch.Generator the recorded step draws from
           [](Program& p, int slot, py::handle gen) {
             TORCH_CHECK(THPGenerator_Check(gen.ptr()), "constant ", slot, " is neither a tensor nor a generator");
             p.set_constant(slot, IValue(reinterpret_cast<THPGenerator*>(gen.ptr())->cdata));
           })
      .def("set_inputs", &Program::set_inputs)
      .def("set_outputs", &Program::set_outputs)
      .def("add_call", &Program::add_call)
      .def("add_list_element", &Program::add_list_element)
      .def("set_dependencies", &Program::set_dependencies)
      .def("set_workers", &Program::set_workers)
      .def_property_readonly("workers", &Program::workers)
      .def_property_readonly("measured", &Program::measured)
      .def_property_readonly("threads_in_use", &Program::threads_in_use)
      .def_property_readonly("why_in_order", &Program::why_in_order)
      .def("measured_us", &Program::measured_us)
      .def("call_times_us", &Program::call_times_us)

      // without the GIL: other Python threads (a node's ROS callbacks) go on during a step
      .def("run", &Program::run, py::call_guard<py::gil_scoped_release>());
}
