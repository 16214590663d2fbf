// A small interpreter for a recorded list of ATen operator calls.
//
// ``learners/traced.py`` records one training step of a learner (its own ``update``:
// forwards, autograd's backward, the optimiser) as the exact sequence of operator calls
// it made, and hands that sequence here. ``run`` replays it through the dispatcher's
// boxed calling convention: the same operators with the same arguments, so the same
// bytes as the recorded Python, without Python, autograd or the optimiser's per-call
// overhead. Nothing in this file knows about any learner.
#include <torch/extension.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <ATen/ScalarOps.h>
#include <c10/core/InferenceMode.h>
#include <torch/csrc/Generator.h>
#include <torch/csrc/jit/python/pybind_utils.h>

#include <string>
#include <vector>

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

class Program {
 public:
  explicit Program(int64_t n_slots) : slots_(n_slots) {}

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

  std::vector<at::Tensor> run(const std::vector<at::Tensor>& inputs) {
    TORCH_CHECK(inputs.size() == inputs_.size(), "expected ", inputs_.size(), " inputs, got ", inputs.size());
    c10::InferenceMode guard;
    for (size_t i = 0; i < inputs.size(); ++i) slots_[inputs_[i]] = inputs[i];
    torch::jit::Stack stack;
    for (auto& call : calls_) {
      if (call.list_source >= 0) {
        const IValue& src = slots_[call.list_source];
        slots_[call.outputs[0]] =
            src.isTuple() ? src.toTupleRef().elements()[call.list_index] : src.toListRef()[call.list_index];
      } else {
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
      for (int s : call.release) slots_[s] = IValue();
    }
    std::vector<at::Tensor> out;
    out.reserve(outputs_.size());
    for (int s : outputs_) out.push_back(slots_[s].toTensor());
    for (int s : inputs_) slots_[s] = IValue();
    return out;
  }

  size_t size() const { return calls_.size(); }

 private:
  std::vector<IValue> slots_;
  std::vector<Call> calls_;
  std::vector<int> inputs_, outputs_;
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
      .def("run", &Program::run)
      .def("__len__", &Program::size);
}
